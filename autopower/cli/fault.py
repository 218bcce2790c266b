"""`autopower fault cut|loss|rate|flap|roam|heal|kill|crash|freeze|thaw|radio|list`: inject faults into a team."""

from __future__ import annotations

import json

import click

from autopower.cli.options import TEAM_NAME
from autopower.launch.faults import MEDIA_CHOICES, PHASE_S, ROAM_MS, request_fault


def _run(request: dict, as_json: bool) -> None:
    reply = request_fault(request, team=click.get_current_context().find_root().meta.get("fault_team"))
    click.echo(json.dumps(reply) if as_json else reply.get("message", "ok"))


_json = click.option("--json", "as_json", is_flag=True, help="Print the reply as JSON.")


def _store_team(ctx, _param, team):
    # `fault cut r1 laptop --team T` reads as naturally as `fault --team T cut r1 laptop` (as in
    # `status --team T`): the group and every subcommand take it; the group's is parsed first
    meta = ctx.find_root().meta
    if team is not None:
        given = meta.get("fault_team")
        if given is not None and given != team:
            raise click.UsageError(f"two teams given: {given!r} before the command, {team!r} after it; give one")
        meta["fault_team"] = team
    return team


def _team(f):
    return click.option("--team", default=None, type=TEAM_NAME, expose_value=False, callback=_store_team,
                        help="Which running team (default: the only one on this machine).")(f)


@click.group("fault")
@_team
def fault() -> None:
    """Inject faults into a team started by `autopower up` (real, silent link cuts; signals)."""


_one_way = click.option("--one-way", is_flag=True,
                        help="Only the packets A sends to B (B to A pass); needs the testbed.")


@fault.command("cut")
@click.argument("a")
@click.argument("b")
@_one_way
@_json
@_team
def fault_cut(a, b, one_way, as_json):
    """Cut the radio link A-B silently (no FIN, no RST: only the Zenoh lease notices)."""
    _run({"op": "cut", "a": a, "b": b, **({"one_way": True} if one_way else {})}, as_json)


@fault.command("loss")
@click.argument("a")
@click.argument("b")
@click.argument("pct", type=click.FloatRange(0, 100, min_open=True))
@_one_way
@_json
@_team
def fault_loss(a, b, pct, one_way, as_json):
    """Drop PCT % (0 < PCT <= 100) of the packets on link A-B at random, both ways (testbed only).

    Replaces the loss set on that direction before; `fault heal A B` removes it.
    """
    _run({"op": "loss", "a": a, "b": b, "pct": pct, "one_way": one_way}, as_json)


@fault.command("rate")
@click.argument("a")
@click.argument("b")
@click.argument("kbps", type=click.FloatRange(0, min_open=True))
@_json
@_team
def fault_rate(a, b, kbps, as_json):
    """Shape link A-B, both ways, to KBPS kbit/s (> 0) × the team's speed-up, e.g. a robot moving away.

    Testbed only, on a point-to-point link; `fault heal A B` restores the medium's rate.
    """
    _run({"op": "rate", "a": a, "b": b, "kbps": kbps}, as_json)


_phase = click.FloatRange(*PHASE_S)


@fault.command("flap")
@click.argument("a")
@click.argument("b")
@click.option("--up", "up_s", type=_phase, required=True, help="Seconds up in each cycle (0.05 to 3600).")
@click.option("--down", "down_s", type=_phase, required=True, help="Seconds down in each cycle (0.05 to 3600).")
@click.option("--for", "for_s", type=click.FloatRange(PHASE_S[0]), default=None,
              help="Stop flapping after this many seconds (default: until `fault heal A B` or the team stops).")
@_json
@_team
def fault_flap(a, b, up_s, down_s, for_s, as_json):
    """Cut link A-B (both ways) for --down seconds, then up for --up seconds, again and again (testbed only).

    It starts down. `fault heal A B`, the end of --for and the team stopping end it with the link up.
    """
    _run({"op": "flap", "a": a, "b": b, "up_s": up_s, "down_s": down_s, "for_s": for_s}, as_json)


@fault.command("roam")
@click.argument("a")
@click.argument("b")
@click.argument("ms", type=click.FloatRange(*ROAM_MS))
@_json
@_team
def fault_roam(a, b, ms, as_json):
    """One outage of MS milliseconds (1 to 60000) on link A-B, which then comes back by itself (testbed only).

    A fast 802.11r roam takes 50-150 ms, a full re-association seconds.
    """
    _run({"op": "roam", "a": a, "b": b, "ms": ms}, as_json)


@fault.command("heal")
@click.argument("a")
@click.argument("b")
@_json
@_team
def fault_heal(a, b, as_json):
    """Bring the link A-B back (a cut, one-way cuts, packet loss, a changed rate, a flap or roam)."""
    _run({"op": "heal", "a": a, "b": b}, as_json)


@fault.command("kill")
@click.argument("robot")
@_json
@_team
def fault_kill(robot, as_json):
    """SIGKILL a robot's agent for good (the robot is lost: `up` does not restart it)."""
    _run({"op": "kill", "robot": robot}, as_json)


@fault.command("crash")
@click.argument("node")
@_json
@_team
def fault_crash(node, as_json):
    """SIGKILL a robot's agent or the base station as a crash: `up` restarts it after a backoff."""
    _run({"op": "crash", "robot": node}, as_json)


@fault.command("freeze")
@click.argument("robot")
@_json
@_team
def fault_freeze(robot, as_json):
    """SIGSTOP a robot's agent (it stops answering; its lease expires)."""
    _run({"op": "freeze", "robot": robot}, as_json)


@fault.command("thaw")
@click.argument("robot")
@_json
@_team
def fault_thaw(robot, as_json):
    """SIGCONT a frozen robot's agent."""
    _run({"op": "thaw", "robot": robot}, as_json)


@fault.command("radio")
@click.argument("robot")
@click.option("--laptop", type=click.Choice(MEDIA_CHOICES), default=None, help="The robot's radio to the base.")
@click.option("--robot", "robot_medium", type=click.Choice(MEDIA_CHOICES), default=None,
              help="The robot's radio to other robots.")
@_json
@_team
def fault_radio(robot, laptop, robot_medium, as_json):
    """A robot's radio hardware fails over (the paper's V.C fault): the base station replans."""
    _run({"op": "radio", "robot": robot, "laptop": laptop, "robot_medium": robot_medium}, as_json)


@fault.command("list")
@click.option("--json", "as_json", is_flag=True, help="Accepted for uniformity: the answer is always JSON "
                                                        "(with it, a failure is JSON on stdout too).")
@_team
def fault_list(as_json):
    """The faults injected so far and the state of every link, as JSON."""
    team = click.get_current_context().find_root().meta.get("fault_team")
    click.echo(json.dumps(request_fault({"op": "list"}, team=team), indent=1))


COMMANDS = [fault]
