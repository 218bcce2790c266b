"""`autopower up`: a whole team on this machine, watched live."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import click

from autopower.cli.live_table import render
from autopower.cli.options import (
    DEFAULT_SPEED,
    INSECURE_OPT,
    build_scenario,
    mission_options,
    parse_pairs,
    warn_insecure,
)
from autopower.errors import AutoPowerError
from autopower.launch.summary import run_summary
from autopower.model.network import build_network


@click.command("up")
@click.argument("scenario_name", default="paper-fig7", metavar="[SCENARIO]")
@click.option("--speed", type=float, default=DEFAULT_SPEED, show_default=True,
              help="Virtual seconds per wall second (missed periods are reported if it is too fast).")
@click.option("--duration", type=float, default=None, help="Stop after this many wall seconds (default: Ctrl-C).")
@click.option("--json", "as_json", is_flag=True, help="No live table; print a JSON summary at the end.")
@mission_options
@click.option("--lease-ms", default=500, show_default=True,
              help="Zenoh lease: a silent cut or a frozen robot is detected after about this long.")
@click.option("--direct-links", is_flag=True,
              help="Connect processes directly (no link proxies: `autopower fault cut` is unavailable).")
@click.option("--ready-timeout", type=float, default=60.0, show_default=True)
@click.option("--log-dir", type=click.Path(file_okay=False), default=None,
              help="Where the children's logs go (default: a new temporary directory).")
@click.option("--until-depleted", is_flag=True, help="Stop when the first robot's battery is empty.")
@click.option("--record-dir", type=click.Path(file_okay=False), default=None,
              help="Record the run with Rerun: every process writes here, merged into DIR/run.rrd at the end.")
@INSECURE_OPT
def up(scenario_name, speed, duration, as_json, energy, energy_scale, accounting, topology, media, pin, no_replan,
       policy, lease_ms, direct_links, ready_timeout, log_dir, until_depleted, record_dir, insecure):
    """Start the base station and every robot's agent on this machine and watch them.

    Ctrl-C stops every process cleanly. With --duration and --json it runs unattended and
    prints a summary (placement, batteries against the model, missed periods, results).
    """
    from autopower.basestation.operator import clear_session, state_dir, write_session
    from autopower.launch.faults import SOCKET_NAME, FaultController, FaultServer
    from autopower.launch.localhost import LocalTeam, TeamSpec

    scenario = build_scenario(scenario_name, energy, energy_scale, accounting)  # fail fast on bad options
    parse_pairs(pin, "--pin", "Loc-2=r1")
    if media:
        build_network(scenario, topology=topology, media=parse_pairs(media, "--media", "laptop-robot=gsm"))
    spec = TeamSpec(scenario=scenario_name, speed=speed, energy=tuple(energy), energy_scale=energy_scale,
                    accounting=accounting, topology=topology, media=tuple(media), pins=tuple(pin),
                    auto_replan=not no_replan, policy=policy,
                    lease_ms=lease_ms, log_dir=log_dir, proxied_links=not direct_links,
                    record_dir=Path(record_dir) if record_dir else None, secure=not insecure)
    warn_insecure(insecure)
    if record_dir:
        Path(record_dir).mkdir(parents=True, exist_ok=True)

    def on_term(signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    team = LocalTeam(spec, scenario)
    started = time.monotonic()
    snap: dict = {}
    failure = None
    interrupted = False
    ready_after = None
    console = None
    control = None
    try:
        team.start()
        control = FaultServer(FaultController(team), state_dir() / f"{SOCKET_NAME}").__enter__()
        write_session({"team": team.team, "connect": [team.base_endpoint], "pid": os.getpid(),
                       "children": {n: c.proc.pid for n, c in team.children.items()},
                       "scenario": scenario.name, "log_dir": str(team.log_dir),
                       "control": str(control.path), **team.session_security()})
        if not as_json:
            from rich.console import Console

            console = Console(stderr=False)
            console.print(f"starting {scenario.name}: base station + {len(scenario.robots)} agents "
                          f"(team {team.team}, logs in {team.log_dir}) …")
        snap = team.wait_ready(ready_timeout)
        ready_after = time.monotonic() - started
        run_started = time.monotonic()

        def done() -> bool:
            if duration is not None and time.monotonic() - run_started >= duration:
                return True
            return bool(until_depleted and snap.get("first_depletion"))

        if as_json:
            while not done():
                time.sleep(0.25)
                team.check_children()
                if until_depleted:
                    snap = team.snapshot()
        else:
            from rich.live import Live

            with Live(render(snap, speed), console=console, refresh_per_second=4, transient=False) as live:
                while not done():
                    time.sleep(0.5)
                    team.check_children()
                    snap = team.snapshot()
                    live.update(render(snap, speed))
            console.print()
        snap = team.snapshot()
    except AutoPowerError as exc:
        if not snap:
            raise
        failure = str(exc)  # report what we saw last, then fail
    except KeyboardInterrupt:
        interrupted = True
        try:
            snap = team.snapshot(timeout_s=1.0) if team.client else snap
        except AutoPowerError:
            pass
    finally:
        if control is not None:
            control.close()
        codes = team.stop()
        clear_session(team.team)
        signal.signal(signal.SIGTERM, previous)
    summary = run_summary(snap, team=team.team, speed=speed, ready_after_s=ready_after or -1.0,
                        wall_s=time.monotonic() - started, exit_codes=codes, log_dir=str(team.log_dir))
    summary["interrupted"] = interrupted
    summary["failure"] = failure
    summary["recording"] = None
    if record_dir:
        from autopower.recording.live import merge_run

        try:
            summary["recording"] = str(merge_run(Path(record_dir)))
        except AutoPowerError as exc:  # the run itself is fine; say why there is no merged file
            summary["recording_error"] = str(exc)
    bad = {n: c for n, c in codes.items() if c not in (0, None)}
    if as_json:
        click.echo(json.dumps(summary, indent=2, default=str))
    else:
        click.echo(f"stopped {len(codes)} processes ({'interrupted' if interrupted else 'done'}); "
                   f"logs in {team.log_dir}")
        if summary["recording"]:
            click.echo(f"recording: {summary['recording']} (autopower replay {summary['recording']})")
        if summary["missed_ratio"] > 0.01:
            click.echo(f"warning: {summary['periods_missed']} source periods missed "
                       f"({summary['missed_ratio']:.1%}); this machine cannot keep up with --speed {speed:g}. "
                       "Lower --speed (and use --energy-scale for shorter missions).", err=True)
    if bad:
        raise AutoPowerError(f"process(es) exited with errors: {bad}; logs in {team.log_dir}")
    if failure:
        raise AutoPowerError(f"{failure} (logs in {team.log_dir})")


COMMANDS = (up,)
