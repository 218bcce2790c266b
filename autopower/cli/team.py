"""`autopower up`: a whole team on this machine, watched live."""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import click

from autopower.cli.live_table import render
from autopower.cli.options import (
    DEFAULT_SPEED,
    INSECURE_OPT,
    LEASE_MS,
    POSITIVE,
    TEAM_NAME,
    build_scenario,
    mission_options,
    parse_pairs,
    stage_workers_option,
    warn_insecure,
)
from autopower.errors import AutoPowerError
from autopower.launch.summary import (
    complete_at_ready,
    every_robot_depleted,
    run_summary,
    status_line,
    supervisor_line,
)
from autopower.launch.supervisor import RestartPolicy
from autopower.model.network import build_network

SNAPSHOT_EVERY_S = 1.0  # how often `up` without a live table asks the base station how things are
SNAPSHOT_AT_REST_S = 5.0  # the same while no chain runs (a snapshot costs the base station too)
STATUS_LINE_EVERY_S = 5.0  # how often it prints a plain status line to a pipe or a log
RECORDING_CHECK_EVERY_S = 2.0  # how often it checks that the recording is still being written


def control_plane_settings(spec, lease_ms: int | None) -> dict:
    """The team's lease, keep-alives, status period and heartbeat: what the scenario's ``[control_plane]``
    says (`model.control_plane`: what the planner charges when it is enabled, with the runtime's
    defaults otherwise), the lease overridden by ``--lease-ms``."""
    return {"lease_ms": lease_ms if lease_ms is not None else round(spec.lease_s * 1000),
            "keep_alive": spec.keep_alives_per_lease, "status_period_s": spec.status_period_s,
            "heartbeat_s": spec.heartbeat_s}


@click.command("up")
@click.argument("scenario_name", default="paper-fig7", metavar="[SCENARIO]")
@click.option("--speed", type=POSITIVE, default=DEFAULT_SPEED, show_default=True,
              help="Virtual seconds per wall second (missed periods are reported if it is too fast).")
@click.option("--duration", type=POSITIVE, default=None, help="Stop after this many wall seconds (default: Ctrl-C).")
@click.option("--json", "as_json", is_flag=True, help="No live table; print a JSON summary at the end.")
@mission_options
@click.option("--lease-ms", default=None, type=LEASE_MS,
              help="Zenoh lease: a silent cut or a frozen robot is detected after about this long "
                   "(default: the scenario's [control_plane] lease_s, 500 ms unless it says otherwise).")
@click.option("--direct-links", is_flag=True,
              help="Connect processes directly (no link proxies: `autopower fault cut` is unavailable).")
@click.option("--team", "team_name", default=None, type=TEAM_NAME,
              help="Name the team (default: a new name); commands pick it with --team.")
@click.option("--ready-timeout", type=POSITIVE, default=60.0, show_default=True)
@click.option("--log-dir", type=click.Path(file_okay=False), default=None,
              help="Where the children's logs go (default: a new temporary directory).")
@click.option("--until-depleted", is_flag=True, help="Stop when the first robot's battery is empty.")
@click.option("--record-dir", type=click.Path(file_okay=False), default=None,
              help="Record the run with Rerun: every process writes here, merged into DIR/run.rrd at the end.")
@click.option("--restart-burst", type=click.IntRange(0, 1000), default=RestartPolicy.burst, show_default=True,
              help="A crashed process is restarted (backoff from 0.2 s, doubling); after more than this many "
                   "crashes within --restart-interval it is given up (0: never restart).")
@click.option("--restart-interval", type=POSITIVE, default=RestartPolicy.interval_s, show_default=True,
              help="Seconds over which --restart-burst counts crashes.")
@click.option("--robot-nice", type=click.IntRange(0, 19), default=0, show_default=True,
              help="Added to every robot agent's nice value (not the base station's): on one machine the "
                   "robots share the cores a real base station has to itself.")
@INSECURE_OPT
@stage_workers_option
def up(scenario_name, speed, duration, as_json, energy, energy_scale, accounting, topology, media, pin, no_replan,
       policy, lease_ms, direct_links, team_name, ready_timeout, log_dir, until_depleted, record_dir, restart_burst,
       restart_interval, robot_nice, insecure, stage_workers):
    """Start the base station and every robot's agent on this machine and watch them.

    Ctrl-C stops every process cleanly. With --duration and --json it runs unattended and
    prints a summary (placement, batteries against the model, missed periods, results).
    A process that crashes is restarted with backoff while the others run on; one that keeps
    crashing is given up (reported; exit 2 at the end).
    """
    from autopower.basestation.operator import running_sessions, team_dir, write_session
    from autopower.launch.faults import SOCKET_NAME, FaultController, FaultServer

    if team_name in running_sessions():  # (which also removes the files of teams whose `up` died)
        raise AutoPowerError(f"team {team_name!r} is already running on this machine; "
                             "choose another --team name or stop that one")
    from autopower.launch.localhost import LocalTeam, TeamSpec

    scenario = build_scenario(scenario_name, energy, energy_scale, accounting, to_run=True)  # fail fast on bad options
    parse_pairs(pin, "--pin", "Loc-2=r1")
    if media:
        build_network(scenario, topology=topology, media=parse_pairs(media, "--media", "laptop-robot=gsm"))
    spec = TeamSpec(scenario=scenario_name, speed=speed, energy=tuple(energy), energy_scale=energy_scale,
                    accounting=accounting, topology=topology, media=tuple(media), pins=tuple(pin),
                    auto_replan=not no_replan, policy=policy, stage_workers=stage_workers,
                    log_dir=log_dir, proxied_links=not direct_links, team=team_name,
                    **control_plane_settings(scenario.control_plane, lease_ms),
                    record_dir=Path(record_dir) if record_dir else None, secure=not insecure, robot_nice=robot_nice,
                    restart=RestartPolicy(burst=restart_burst, interval_s=restart_interval))
    warn_insecure(insecure)
    if record_dir:
        from autopower.recording.health import check_record_dir

        check_record_dir(record_dir)  # refused here, in one line, before any process starts

    def on_term(signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    team = LocalTeam(spec, scenario)
    started = time.monotonic()
    snap: dict = {}
    failure = None
    interrupted = False
    ready_after = at_ready = None
    all_depleted = False
    recording_failure = None
    console = None
    control = None
    try:
        team.start()
        control = FaultServer(FaultController(team), team_dir(team.team) / SOCKET_NAME).__enter__()
        write_session({"team": team.team, "connect": [team.base_endpoint], "pid": os.getpid(),
                       "children": {n: c.proc.pid for n, c in team.children.items()},
                       "scenario": scenario.name, "log_dir": str(team.log_dir),
                       "control": str(control.path), **team.session_security()})
        if not as_json:
            from rich.console import Console

            console = Console(stderr=False)
            console.print(f"starting {scenario.name}: base station + {len(scenario.robots)} agents "
                          f"(team {team.team}, logs in {team.log_dir}) …")
        if record_dir and not as_json:
            click.echo(f"recording into {record_dir}; if this run is cut short, "
                       f"`autopower recording merge {record_dir}` builds {Path(record_dir) / 'run.rrd'}")
        snap = at_ready = team.wait_ready(ready_timeout)
        ready_after = time.monotonic() - started
        run_started = last_poll = last_record_check = time.monotonic()
        nodes = [scenario.basestation] + [r.name for r in scenario.robots]

        def done() -> bool:
            nonlocal all_depleted, recording_failure, last_record_check
            if duration is not None and time.monotonic() - run_started >= duration:
                return True
            if record_dir and time.monotonic() - last_record_check >= RECORDING_CHECK_EVERY_S:
                from autopower.recording.health import recording_problem

                last_record_check = time.monotonic()
                recording_failure = recording_problem(record_dir, nodes)
                if recording_failure:  # stop cleanly now rather than run on without a record
                    snap["recording_error"] = recording_failure
                    return True
            all_depleted = every_robot_depleted(snap)  # the mission is over: nothing left to watch
            return all_depleted or bool(until_depleted and snap.get("first_depletion"))

        if as_json or not sys.stdout.isatty():  # a pipe or a log: no live table, a plain line now and then
            last_line = time.monotonic()
            while not done():
                # asleep until the next thing due (a snapshot, a line, the end) or a supervisor event
                # (printed as it happens), not woken every 0.25 s to look
                due = [last_poll + (SNAPSHOT_EVERY_S if snap.get("running") else SNAPSHOT_AT_REST_S)]
                due += [] if as_json else [last_line + STATUS_LINE_EVERY_S]
                due += [run_started + duration] if duration is not None else []
                due += [last_record_check + RECORDING_CHECK_EVERY_S] if record_dir else []
                team.wait_for_news(min(due) - time.monotonic())
                for event in team.check_children():  # a crash restarts that process; the rest run on
                    click.echo(f"supervisor: {event.line()}", err=True)
                now = time.monotonic()
                if now - last_poll >= (SNAPSHOT_EVERY_S if snap.get("running") else SNAPSHOT_AT_REST_S):
                    last_poll = now
                    try:
                        snap = team.snapshot(timeout_s=2.0)
                    except AutoPowerError:  # a busy base station answers late (or is restarting): keep the last one
                        pass
                    complete_at_ready(at_ready, snap)
                snap["supervision"] = team.supervision()
                if not as_json and now - last_line >= STATUS_LINE_EVERY_S:
                    click.echo(status_line(snap, speed))
                    last_line = now
        else:
            from rich.live import Live

            with Live(render(snap, speed), console=console, refresh_per_second=4, transient=False) as live:
                while not done():
                    time.sleep(0.5)
                    team.check_children()
                    try:
                        snap = team.snapshot(timeout_s=2.0)
                    except AutoPowerError:  # the base station is busy, or crashed (restarting or given up,
                        pass                # which the supervisor's line says): show the last view
                    complete_at_ready(at_ready, snap)
                    snap["supervision"] = team.supervision()
                    live.update(render(snap, speed))
                live.update(render(snap, speed))
            console.print()
        snap = team.snapshot()
        complete_at_ready(at_ready, snap)
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
        codes = end_session(team, control, previous)
    summary = run_summary(snap, team=team.team, speed=speed, ready_after_s=ready_after or -1.0, at_ready=at_ready,
                        wall_s=time.monotonic() - started, exit_codes=codes, log_dir=str(team.log_dir))
    summary["interrupted"] = interrupted
    summary["all_depleted"] = all_depleted
    summary["link_bytes"] = team.link_bytes()
    summary["supervision"] = supervision = team.supervision()
    given_up = supervision.get("given_up") or {}
    summary["failure"] = failure
    summary["recording"] = None
    summary["recording_error"] = f"recording failed during the run: {recording_failure}" if recording_failure else None
    if record_dir:
        from autopower.recording.live import merge_run

        try:
            summary["recording"] = str(merge_run(Path(record_dir)))
        except (AutoPowerError, OSError) as exc:  # the run itself is fine; say why there is no merged file
            summary["recording_error"] = "; ".join(filter(None, [summary["recording_error"], str(exc)]))
    bad = {n: c for n, c in codes.items() if c not in (0, None) and n not in given_up}
    error = (f"gave up restarting {', '.join(f'{n} ({why})' for n, why in given_up.items())}; the rest of the "
             f"team ran on; logs in {team.log_dir}" if given_up
             else team.exit_report(bad) if bad
             else f"{failure} (logs in {team.log_dir})" if failure
             else f"the recording failed ({recording_failure}); the team was stopped cleanly" if recording_failure
             else None)
    if as_json:
        if error:
            summary.update(error=error, exit_code=2)
        click.echo(json.dumps(summary, indent=2, default=str))
    else:
        why = ("interrupted" if interrupted else "recording failed" if recording_failure
               else "every robot depleted" if all_depleted else "done")
        click.echo(f"stopped {len(codes)} processes ({why}); logs in {team.log_dir}")
        if supervision.get("crashes"):
            click.echo(supervisor_line(supervision))
        if summary["recording"]:
            click.echo(f"recording: {summary['recording']} (autopower replay {summary['recording']})")
        if summary["recording_error"]:
            click.echo(f"recording: NOT complete: {summary['recording_error']}", err=True)
            if not summary["recording"]:
                click.echo(f"recording: what the processes wrote is in {record_dir}; "
                           f"`autopower recording merge {record_dir}` builds run.rrd from it", err=True)
        for warning in summary["warnings"]:
            click.echo(f"warning: {warning}", err=True)
    if error:
        # the summary above is the one JSON object (it carries the error); the line goes to stderr
        click.echo(f"error: {error}", err=True)
        sys.exit(2)


COMMANDS = (up,)


def end_session(team, control, previous_sigterm) -> dict:
    """Stop a team `up` or `testbed up` started: its fault socket first (no fault lands on a
    stopping team), the processes, the session file `autopower status` finds it by, and our
    SIGTERM handler. Returns each process's exit code."""
    from autopower.basestation.operator import clear_session

    if control is not None:
        control.close()
    codes = team.stop()
    clear_session(team.team)
    signal.signal(signal.SIGTERM, previous_sigterm)
    return codes
