"""`autopower testbed up|down`: the team in network namespaces over links shaped like its radios."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import click

from autopower.cli.live_table import render
from autopower.cli.options import DEFAULT_SPEED, TRANSPORT_OPT, build_scenario, parse_pairs
from autopower.cli.team import SNAPSHOT_EVERY_S, end_session
from autopower.errors import AutoPowerError
from autopower.launch.summary import at_ready_complete, complete_at_ready, run_summary


@click.group("testbed")
def testbed() -> None:
    """Each node in its own network namespace, each link a veth pair shaped to its radio (needs root)."""


@testbed.command("up")
@click.argument("scenario_name", default="paper-fig7", metavar="[SCENARIO]")
@click.option("--speed", type=float, default=DEFAULT_SPEED, show_default=True,
              help="Virtual seconds per wall second; every link is shaped to its medium's rate x this.")
@click.option("--duration", type=float, default=None, help="Stop after this many wall seconds (default: Ctrl-C).")
@click.option("--json", "as_json", is_flag=True, help="No live table; print a JSON summary at the end.")
@click.option("--lease-ms", default=1000, show_default=True, help="Zenoh lease on every node.")
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None)
@click.option("--media", multiple=True, metavar="GROUP=MEDIUM", help="Fix a link group's medium, e.g. laptop-robot=gsm.")
@click.option("--pin", multiple=True, metavar="STAGE=NODE", help="Keep a stage on a node (repeatable).")
@click.option("--no-shaping", is_flag=True, help="Links at full veth speed (for comparison).")
@click.option("--ready-timeout", type=float, default=90.0, show_default=True)
@click.option("--log-dir", type=click.Path(file_okay=False), default=None)
@click.option("--record-dir", type=click.Path(file_okay=False), default=None,
              help="Record the run with Rerun: every process writes here, merged into DIR/run.rrd at the end.")
@TRANSPORT_OPT
def testbed_up(scenario_name, speed, duration, as_json, lease_ms, topology, media, pin, no_shaping, ready_timeout,
               log_dir, record_dir, transport):
    """Start the team in the testbed and watch it; Ctrl-C (or --duration) removes every namespace and link.

    `autopower status`, `chain`, `migrate`, `fault cut|heal|kill|freeze|thaw` and `replay` work on
    it as on `autopower up`; a cut drops the link's packets silently. Only here: `fault loss A B PCT
    [--one-way]` (random packet loss), `fault cut A B --one-way`, `fault rate A B KBPS`, `fault flap
    A B --up S --down S [--for S]` and `fault roam A B MS`.
    """
    from autopower.basestation.operator import team_dir, write_session
    from autopower.launch.faults import SOCKET_NAME, FaultController, FaultServer
    from autopower.launch.localhost import TeamSpec
    from autopower.launch.netns import require_root
    from autopower.launch.testbed import TestbedTeam

    require_root()
    scenario = build_scenario(scenario_name)
    parse_pairs(pin, "--pin", "Loc-2=r1")
    parse_pairs(media, "--media", "laptop-robot=gsm")
    spec = TeamSpec(scenario=scenario_name, speed=speed, topology=topology, media=tuple(media), pins=tuple(pin),
                    lease_ms=lease_ms, log_dir=log_dir, record_dir=Path(record_dir) if record_dir else None,
                    transport=transport)
    if record_dir:
        from autopower.recording.health import check_record_dir

        check_record_dir(record_dir)  # refused here, in one line, before any namespace is made
    recording = _RecordingWatch(record_dir, [scenario.basestation] + [r.name for r in scenario.robots])

    def on_term(signum, _frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    team = TestbedTeam(spec, scenario, shaping=not no_shaping)
    started, snap, ready_after, at_ready, control, interrupted = time.monotonic(), {}, None, None, None, False
    try:
        team.start()
        control = FaultServer(FaultController(team), team_dir(team.team) / SOCKET_NAME).__enter__()
        write_session({"team": team.team, "connect": [team.base_endpoint], "pid": os.getpid(),
                       "children": {n: c.proc.pid for n, c in team.children.items()}, "scenario": scenario.name,
                       "log_dir": str(team.log_dir), "control": str(control.path), **team.session_security()})
        if not as_json:
            click.echo(f"testbed {team.net.run_id}: {len(team.nodes)} namespaces, {len(team.net.links)} links "
                       f"({'shaped to rate x ' + format(speed, 'g') if not no_shaping else 'unshaped'}), "
                       f"mutual TLS{' over QUIC' if transport == 'quic' else ''} + access control; team {team.team}, logs in {team.log_dir}")
            if record_dir:
                click.echo(f"recording into {record_dir}; if this run is cut short, "
                           f"`autopower recording merge {record_dir}` builds {Path(record_dir) / 'run.rrd'}")
        snap = at_ready = team.wait_ready(ready_timeout)
        ready_after = time.monotonic() - started
        run_started = time.monotonic()

        def running() -> bool:
            return (duration is None or time.monotonic() - run_started < duration) and not recording.failed()

        if as_json:
            last_poll = time.monotonic()
            while running():
                time.sleep(0.25)
                team.check_children()
                # a robot the ready snapshot had not heard from yet is compared from its first status
                # after it, as under `up` (not from the last one: no time between the two, no figure)
                if not at_ready_complete(at_ready) and time.monotonic() - last_poll >= SNAPSHOT_EVERY_S:
                    last_poll = time.monotonic()
                    try:
                        complete_at_ready(at_ready, team.snapshot(timeout_s=2.0))
                    except AutoPowerError:  # a busy base station answers late: ask again
                        pass
        else:
            from rich.console import Console
            from rich.live import Live

            with Live(render(snap, speed), console=Console(), refresh_per_second=4) as live:
                while running():
                    time.sleep(0.5)
                    team.check_children()
                    snap = team.snapshot()
                    complete_at_ready(at_ready, snap)
                    live.update(render(snap, speed))
        snap = team.snapshot()
        complete_at_ready(at_ready, snap)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        codes = end_session(team, control, previous)
    summary = run_summary(snap, team=team.team, speed=speed, ready_after_s=ready_after or -1.0, at_ready=at_ready,
                          wall_s=time.monotonic() - started, exit_codes=codes, log_dir=str(team.log_dir))
    summary.update(interrupted=interrupted, testbed=team.net.run_id, shaped=not no_shaping, network_s=team.network_s,
                   supervision=team.supervision(),  # crashed children restarted in their namespace
                   **team.net.describe(), **recording.merge())
    if as_json:
        click.echo(json.dumps(summary, indent=2, default=str))
    else:
        click.echo(f"stopped; namespaces and links removed; logs in {team.log_dir}")
        if summary.get("recording"):
            click.echo(f"recording: {summary['recording']} (autopower replay {summary['recording']})")
        if summary.get("recording_error"):
            click.echo(f"recording: NOT complete: {summary['recording_error']}", err=True)
    if recording.problem:
        raise AutoPowerError(f"the recording failed ({recording.problem}); the testbed was stopped cleanly")
    given_up = summary["supervision"].get("given_up") or {}
    if given_up:
        raise AutoPowerError(f"gave up restarting {', '.join(f'{n} ({why})' for n, why in given_up.items())}; "
                             f"logs in {team.log_dir}")
    bad = {n: c for n, c in codes.items() if c not in (0, None)}
    if bad:
        raise AutoPowerError(team.exit_report(bad))


class _RecordingWatch:
    """With --record-dir: whether the recording still gets written (checked now and then), and
    the merge at the end. A run whose recording fails is stopped cleanly rather than run on
    unrecorded, as `autopower up` does."""

    CHECK_EVERY_S = 2.0

    def __init__(self, record_dir: str | None, nodes: list[str]):
        self.record_dir, self.nodes = record_dir, nodes
        self.problem: str | None = None
        self._checked = time.monotonic()

    def failed(self) -> bool:
        if self.record_dir and self.problem is None and time.monotonic() - self._checked >= self.CHECK_EVERY_S:
            from autopower.recording.health import recording_problem

            self._checked = time.monotonic()
            self.problem = recording_problem(self.record_dir, self.nodes)
        return self.problem is not None

    def merge(self) -> dict:
        """``recording`` (the merged file) and ``recording_error`` for the summary; nothing without --record-dir."""
        if not self.record_dir:
            return {}
        from autopower.recording.live import merge_run

        out = {"recording": None, "recording_error": f"recording failed during the run: {self.problem}"
               if self.problem else None}
        try:
            out["recording"] = str(merge_run(Path(self.record_dir)))
        except (AutoPowerError, OSError) as exc:  # the run itself is fine; say why there is no merged file
            out["recording_error"] = "; ".join(filter(None, [out["recording_error"], str(exc)]))
        return out


@testbed.command("down")
@click.option("--json", "as_json", is_flag=True)
def testbed_down(as_json):
    """Remove the namespaces and links a killed `testbed up` left (never those of a running one)."""
    from autopower.basestation.operator import state_dir
    from autopower.launch.netns import cleanup_stale

    removed = cleanup_stale(state_dir())
    if as_json:
        click.echo(json.dumps({"removed": removed}))
    else:
        click.echo(f"removed {len(removed)} namespace(s)" + (f": {', '.join(removed)}" if removed else ""))


COMMANDS = (testbed,)
