"""`autopower deploy init`: certificates, Zenoh configurations and service units for a fleet."""

from __future__ import annotations

import json
from pathlib import Path

import click

from autopower.cli.options import SCENARIO_ARG


@click.group("deploy")
def deploy() -> None:
    """Put a team on real hosts: one directory per node to copy to it (see docs/deploying/robots.md)."""


@deploy.command("init")
@SCENARIO_ARG
@click.option("--fleet", "fleet_file", required=True, type=click.Path(dir_okay=False), metavar="FLEET.toml",
              help="Which host each node runs on (see deploy/fleet.example.toml).")
@click.option("--out", required=True, type=click.Path(file_okay=False), metavar="DIR",
              help="Where to write the CA and one directory per node (created 0700).")
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None,
              help="Whose links become connections (default: the scenario's).")
@click.option("--install-dir", default="/etc/autopower", show_default=True,
              help="Where a node's directory will live on its host (paths in zenoh.json5 and the unit).")
@click.option("--exec", "exec_path", default="/opt/autopower/.venv/bin/autopower", show_default=True,
              help="The autopower command on the hosts (the unit's ExecStart).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
def deploy_init(scenario, fleet_file, out, topology, install_dir, exec_path, as_json):
    """Write a team CA and, per node: key + certificate, Zenoh configuration (json5), systemd unit.

    Every link is mutual TLS against the new CA, scouting is off, each node connects to its
    neighbours in the scenario's topology, and access control is default deny. Keys are
    written 0600 and never printed; the CA key stays in DIR/ca (keep it off the robots).
    """
    from autopower.deploy.bundle import write_bundle
    from autopower.deploy.fleet import load_fleet

    fleet = load_fleet(Path(fleet_file))
    written = write_bundle(Path(out), scenario, fleet, topology=topology, install_dir=install_dir,
                           exec_path=exec_path)
    if as_json:
        click.echo(json.dumps({"team": fleet.team, "ca": str(Path(out) / "ca" / "ca.pem"),
                               "nodes": {n: str(d) for n, d in written.items()}}, indent=2))
        return
    click.echo(f"team {fleet.team}: CA in {Path(out) / 'ca'} (keep ca.key on this machine only)")
    for node, directory in written.items():
        click.echo(f"  {node:<10} {directory}  -> copy to {install_dir} on "
                   f"{fleet.nodes[node].address if node in fleet.nodes else 'the operator machine'}")
    click.echo("next: see docs/deploying/robots.md")


COMMANDS = (deploy,)
