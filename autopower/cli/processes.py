"""The team's processes: `autopower agent` and `autopower basestation`.

``python -m autopower.cli.processes agent|basestation ...`` runs them without the rest of the CLI;
this is how `up` starts its children.
"""

from __future__ import annotations

import logging
import os
import signal
import sys

import click

from autopower.cli.options import (
    DEFAULT_SPEED,
    NON_NEGATIVE,
    POSITIVE,
    build_scenario,
    check_heartbeat,
    fleet_dir,
    mission_options,
    network_options,
    parse_pairs,
    secure,
    setup_logging,
    stage_workers_option,
    stage_workers_wanted,
    zenoh_settings,
)
from autopower.errors import AutoPowerError
from autopower.model.network import build_network
from autopower.runtime.memory import keep_large_buffers


def run_until_signalled(process, duration: float | None) -> str:
    def on_signal(signum, _frame):
        process.request_stop(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    process.events.wake_on_signals()  # its loop then sleeps until its next due event, not in slices
    keep_large_buffers()  # frames and the components' arrays reuse heap memory (`runtime.memory`)
    folder = os.environ.get("AUTOPOWER_PROFILE_DIR")
    if not folder:
        return process.run(duration)
    # where the loop's CPU goes (docs/performance.md): cProfile timed by this thread's CPU
    # time, so waiting and other processes' load do not count; written when the loop ends
    import cProfile
    import time

    profiler = cProfile.Profile(time.thread_time)
    try:
        return profiler.runcall(process.run, duration)
    finally:
        name = getattr(process, "node", None) or getattr(process.config, "robot", "process")
        profiler.dump_stats(os.path.join(folder, f"{name}-{os.getpid()}.prof"))


def exit_now(message: str) -> None:
    """Leave without interpreter teardown once the session is closed.

    Teardown resets signal handlers (a SIGTERM from `up` arriving then would kill the process
    with -15 instead of a clean 0) and can wait on the transport's threads; there is nothing
    left to clean up at this point.
    """
    click.echo(message, err=True)
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


@click.command("agent")
@click.option("--robot", "--node", "robot", default=None,
              help="Which robot of the scenario this agent is (with --fleet: which node directory).")
@network_options
@stage_workers_option
def agent(robot, scenario_name, team, listen, connect, lease_ms, keep_alive, status_period, heartbeat, duration, parent_pid, log_level,
          record_dir, stage_workers):
    """Run one robot's agent: host components, meter the battery, forward, publish status."""
    from autopower.agent.process import Agent, AgentConfig

    check_heartbeat(status_period, heartbeat)
    setup_logging(log_level)
    robot, scenario_name, team, zenoh = _joining(robot, scenario_name, team, listen, connect, lease_ms, keep_alive, "robot")
    if robot is None:
        raise AutoPowerError("which robot? pass --robot NAME (or --fleet DIR --node NAME)")
    scenario = build_scenario(scenario_name, to_run=True)  # imports and registers its plug-in components
    from autopower.agent.resume import AGENTS_DIR
    from autopower.basestation.operator import team_dir

    config = AgentConfig(robot=robot, scenario=scenario, team=team,
                         zenoh=secure(zenoh, robot, scenario, team),
                         status_period_s=status_period, status_rest_period_s=heartbeat, parent_pid=parent_pid,
                         resume_path=team_dir(team) / AGENTS_DIR / f"{robot}.json")
    recorder, bus = _recording_bus(record_dir, robot, scenario, config.zenoh)
    try:
        with Agent(config, bus=bus, stage_workers=stage_workers_wanted(stage_workers, basestation=False)) as process:
            if recorder is not None:
                recorder.attach(process.runtime)
            reason = run_until_signalled(process, duration)
            if recorder is not None:
                recorder.record_stop(process.runtime)
    finally:
        if bus is not None:
            bus.close()  # flushes the recording: before os._exit
    exit_now(f"agent {robot} stopped: {reason}")


def _joining(node, scenario_name, team, listen, connect, lease_ms, keep_alive, role: str):
    """(node, scenario, team, Zenoh settings): from --fleet DIR when given, else the command line."""
    fleet = fleet_dir()
    if fleet is None:
        return node, scenario_name, team, zenoh_settings(listen, connect, lease_ms, keep_alive)
    from autopower.deploy.bundle import load_bundle

    bundle = load_bundle(fleet, node)
    if bundle.role != role:
        raise AutoPowerError(f"{bundle.directory} is the {bundle.role} {bundle.node!r}, not a {role}")
    if listen or connect:
        raise AutoPowerError("--listen/--connect come from --fleet DIR; edit the fleet file and run deploy init again")
    return bundle.node, bundle.scenario, bundle.team, bundle.zenoh


def _recording_bus(record_dir, node: str, scenario, zenoh):
    """(recorder, tapped bus) when recording, else (None, None): the process opens its own bus."""
    if not record_dir:
        return None, None
    from autopower.recording.live import open_recorder
    from autopower.runtime.bus import ZenohBus

    recorder = open_recorder(record_dir, node, scenario=scenario)
    return recorder, recorder.tap(ZenohBus(zenoh))


@click.command("basestation")
@network_options
@click.option("--node", default=None, help="With --fleet: which node directory (the base station's name).")
@click.option("--speed", type=POSITIVE, default=DEFAULT_SPEED, show_default=True,
              help="Virtual seconds per wall second.")
@mission_options
@click.option("--replan-interval", type=POSITIVE, default=600.0, show_default=True,
              help="Virtual seconds between re-plans with the remaining energies.")
@click.option("--start-grace", type=NON_NEGATIVE, default=30.0, show_default=True,
              help="Wall seconds to wait for every robot before starting without the missing ones.")
@stage_workers_option
def basestation(scenario_name, team, listen, connect, lease_ms, keep_alive, status_period, heartbeat, duration, parent_pid, log_level,
                record_dir, node, speed, energy, energy_scale, accounting, topology, media, pin, no_replan, policy,
                replan_interval, start_grace, stage_workers):
    """Run the base station: plan, place and migrate components; the operator's sink."""
    from autopower.basestation.coordinator import CoordinatorConfig
    from autopower.basestation.operator import team_dir
    from autopower.basestation.process import BaseStation, BaseStationConfig
    from autopower.node.held_store import HeldStore
    from autopower.node.ports import NodeStores
    from autopower.node.runtime import NodeRuntime
    from autopower.node.sink_store import SinkStore

    check_heartbeat(status_period, heartbeat)
    setup_logging(log_level)
    if not speed > 0:
        raise AutoPowerError(f"--speed must be > 0, got {speed}")
    _, scenario_name, team, zenoh = _joining(node, scenario_name, team, listen, connect, lease_ms, keep_alive, "basestation")
    scenario = build_scenario(scenario_name, energy, energy_scale, accounting, to_run=True)
    zenoh = secure(zenoh, scenario.basestation, scenario, team)
    media_choice = parse_pairs(media, "--media", "laptop-robot=gsm") or None
    if media_choice:
        build_network(scenario, topology=topology, media=media_choice)  # unknown group or medium -> ScenarioError
    coordinator = CoordinatorConfig(speed=speed, topology=topology, media=media_choice,
                                    pins=parse_pairs(pin, "--pin", "Loc-2=r1"),
                                    auto_replan=not no_replan, replan_interval_s=replan_interval,
                                    start_grace_s=start_grace, policy=policy,
                                    # listen to a running team for two status periods and a lease
                                    learn_team_s=2 * status_period + zenoh.lease_ms / 1000)
    # what survives a restart (incarnation, the operator sink's ledgers): the team's state directory
    state = team_dir(team)
    config = BaseStationConfig(scenario=scenario, team=team, zenoh=zenoh, state_dir=state,
                               coordinator=coordinator, status_period_s=status_period, status_rest_period_s=heartbeat,
                               parent_pid=parent_pid)

    workers = stage_workers_wanted(stage_workers, basestation=True, speed=speed)

    def host(**kwargs) -> NodeRuntime:
        stores = NodeStores(sink_store=SinkStore(state / "sinks.json"),
                            # results it holds for a robot's chain whose sink is out of reach: a
                            # restart takes them back
                            held_store=HeldStore(state / "basestation.held", background=True))
        return NodeRuntime(**kwargs, stage_workers=workers, stores=stores)

    recorder, bus = _recording_bus(record_dir, scenario.basestation, scenario, config.zenoh)
    try:
        with BaseStation(config, host_factory=host, bus=bus) as process:
            if recorder is not None:
                recorder.attach(process.runtime)
            reason = run_until_signalled(process, duration)
            if recorder is not None:
                recorder.record_stop(process.runtime)
    finally:
        if bus is not None:
            bus.close()
    exit_now(f"base station stopped: {reason}")


COMMANDS = (agent, basestation)


@click.group()
def processes() -> None:
    """One process of a team (normally reached through `autopower`)."""


for _command in COMMANDS:
    processes.add_command(_command)


def main() -> None:
    """``python -m autopower.cli.processes ...``: how `up` starts its children."""
    from autopower.cli.entry import run_command

    run_command(processes)


if __name__ == "__main__":
    main()
