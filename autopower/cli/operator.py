"""Operator commands against the running team: `status`, `chain enable|disable`, `migrate`."""

from __future__ import annotations

import json

import click

from autopower.cli.live_table import render
from autopower.cli.options import operator_options
from autopower.errors import AutoPowerError


def _client(team: str | None, connect: tuple[str, ...]):
    from autopower.basestation.operator import OperatorClient, read_session
    from autopower.cli.options import fleet_dir

    if fleet_dir() is not None:
        from autopower.deploy.bundle import load_bundle

        bundle = load_bundle(fleet_dir(), "operator")
        return OperatorClient(team or bundle.team, settings=bundle.zenoh)
    # an endpoint and a team name reach any base station; else a local team
    session = read_session(team) if not team or not connect else {}
    team = team or session["team"]
    connect = connect or tuple(session["connect"])
    return OperatorClient(team, connect=connect, settings=operator_session_settings(session, connect))


def operator_session_settings(session: dict, connect: tuple[str, ...]):
    """The operator's mutual-TLS client settings when the running team (`up`) is secure, else None."""
    from autopower.runtime.bus import TlsFiles, ZenohSettings

    tls = session.get("operator_tls")
    if not tls:
        return None
    return ZenohSettings(connect=tuple(connect), tls=TlsFiles(**tls))


def _send(command, team, connect, timeout) -> dict:
    with _client(team, connect) as client:
        reply = client.request(command, timeout)
    if not reply.ok:
        raise AutoPowerError(reply.message)
    click.echo(reply.message)
    return reply.snapshot


@click.group("chain")
def chain() -> None:
    """Switch an application chain on or off in the running team (the base station replans)."""


@chain.command("enable")
@click.argument("name")
@operator_options
def chain_enable(name, team, connect, timeout):
    """Run chain NAME again."""
    from autopower.protocol import ChainCommand

    _send(ChainCommand(chain=name, enabled=True), team, connect, timeout)


@chain.command("disable")
@click.argument("name")
@operator_options
def chain_disable(name, team, connect, timeout):
    """Stop chain NAME (e.g. Blob-2 once the victims are found)."""
    from autopower.protocol import ChainCommand

    _send(ChainCommand(chain=name, enabled=False), team, connect, timeout)


@click.command("migrate")
@click.argument("stage", required=False)
@click.argument("node", required=False)
@click.option("--auto", "auto", is_flag=True, help="Clear every pin: placement follows the planner again.")
@operator_options
def migrate(stage, node, auto, team, connect, timeout):
    """Pin STAGE to NODE: a live migration that holds until `migrate --auto`."""
    from autopower.protocol import AutoCommand, MigrateCommand

    if auto == bool(stage or node) or (not auto and not (stage and node)):
        raise AutoPowerError("use `autopower migrate STAGE NODE` or `autopower migrate --auto`")
    command = AutoCommand() if auto else MigrateCommand(stage=stage, to_node=node)
    _send(command, team, connect, timeout)


@click.command("status")
@operator_options
@click.option("--json", "as_json", is_flag=True)
def status(team, connect, timeout, as_json):
    """Show the running team's status once."""
    with _client(team, connect) as client:
        snap = client.snapshot(timeout)
    if not connect:  # a team of `up` on this machine: what its supervisor restarted (the base station cannot know)
        from autopower.launch.faults import request_fault

        try:
            snap["supervision"] = request_fault({"op": "list"}, timeout_s=2.0, team=team).get("supervision")
        except AutoPowerError:
            snap["supervision"] = None
    if as_json:
        click.echo(json.dumps(snap, indent=2, default=str))
    else:
        from rich.console import Console

        Console().print(render(snap, (snap.get("mission") or {}).get("speed", 1.0)))



COMMANDS = (status, chain, migrate)
