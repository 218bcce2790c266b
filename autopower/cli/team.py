"""The runtime's commands: `agent`, `basestation`, `up`, `chain enable|disable`, `migrate`, `status`.

They are plain click commands; the CLI root registers them (``cli.add_command(up)``, ...).
``python -m autopower.cli.team ...`` runs them without the root, which is how
`up` starts its children.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import time
from pathlib import Path

import click

from autopower.errors import AutoPowerError
from autopower.model.scenario import Scenario, load_scenario
from autopower.policies import POLICY_NAMES

log = logging.getLogger("autopower.runtime")

DEFAULT_SPEED = 10.0  # two 4 Hz blob chains at 10x = 80 frames of 230 KB a second: what 2 cores keep up with


# ---------------------------------------------------------------------------------------------
# shared option handling
# ---------------------------------------------------------------------------------------------


def parse_pairs(values: tuple[str, ...], what: str, example: str) -> dict[str, str]:
    out = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise AutoPowerError(f"{what} {item!r}: expected NAME=VALUE, e.g. {what} {example}")
        out[key.strip()] = value.strip()
    return out


def build_scenario(name: str, energy: tuple[str, ...] = (), energy_scale: float | None = None,
                   accounting: str | None = None) -> Scenario:
    """The scenario with energy overrides (absolute, then scaled) and an accounting mode."""
    scenario = load_scenario(name)
    if energy:
        joules = {}
        for robot, value in parse_pairs(energy, "--energy", "r1=32000").items():
            try:
                joules[robot] = float(value)
            except ValueError:
                raise AutoPowerError(f"--energy {robot}={value}: not a number of joules") from None
        scenario = scenario.with_energies(joules)
    if energy_scale is not None:
        if not energy_scale > 0:
            raise AutoPowerError(f"--energy-scale must be > 0, got {energy_scale}")
        scenario = scenario.with_energies({r.name: r.energy_j * energy_scale for r in scenario.robots})
    return scenario.with_accounting(accounting)


def setup_logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def zenoh_settings(listen: tuple[str, ...], connect: tuple[str, ...], lease_ms: int):
    from autopower.runtime.bus import ZenohSettings

    if lease_ms < 100:
        raise AutoPowerError(f"--lease-ms {lease_ms} is too short; use >= 100 ms")
    return ZenohSettings(listen=tuple(listen), connect=tuple(connect), lease_ms=lease_ms)


def run_until_signalled(process, duration: float | None) -> str:
    def on_signal(signum, _frame):
        process.request_stop(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    return process.run(duration)


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


def network_options(f):
    f = click.option("--scenario", "scenario_name", default="paper-fig7", show_default=True,
                     help="Built-in scenario name or path to a .toml file.")(f)
    f = click.option("--team", default="default", show_default=True,
                     help="Team name: every key is under autopower/<team>/.")(f)
    f = click.option("--listen", multiple=True, metavar="ENDPOINT",
                     help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable).")(f)
    f = click.option("--connect", multiple=True, metavar="ENDPOINT",
                     help="Zenoh endpoint of a peer to connect to (repeatable; peers do not relay).")(f)
    f = click.option("--lease-ms", default=1000, show_default=True,
                     help="Zenoh lease: a frozen peer or cut link is noticed after about this long.")(f)
    f = click.option("--status-period", default=0.5, show_default=True, help="Wall seconds between status messages.")(f)
    f = click.option("--duration", type=float, default=None, help="Stop after this many wall seconds.")(f)
    f = click.option("--parent-pid", type=int, default=None, hidden=True)(f)
    f = click.option("--record-dir", type=click.Path(file_okay=False), default=None,
                     help="Write this process's Rerun recording into DIR (the run's shared recording id).")(f)
    f = click.option("--log-level", default="info", show_default=True,
                     type=click.Choice(["debug", "info", "warning", "error"]))(f)
    return f


# ---------------------------------------------------------------------------------------------
# agent, basestation
# ---------------------------------------------------------------------------------------------


@click.command("agent")
@click.option("--robot", required=True, help="Which robot of the scenario this agent is.")
@network_options
def agent(robot, scenario_name, team, listen, connect, lease_ms, status_period, duration, parent_pid, log_level,
          record_dir):
    """Run one robot's agent: host components, meter the battery, forward, publish status."""
    from autopower.agent.process import Agent, AgentConfig

    setup_logging(log_level)
    scenario = load_scenario(scenario_name)
    config = AgentConfig(robot=robot, scenario=scenario, team=team,
                         zenoh=zenoh_settings(listen, connect, lease_ms),
                         status_period_s=status_period, parent_pid=parent_pid)
    recorder, bus = _recording_bus(record_dir, robot, scenario, config.zenoh)
    try:
        with Agent(config, bus=bus) as process:
            if recorder is not None:
                recorder.attach(process.runtime)
            reason = run_until_signalled(process, duration)
    finally:
        if bus is not None:
            bus.close()  # flushes the recording: before os._exit
    exit_now(f"agent {robot} stopped: {reason}")


def _recording_bus(record_dir, node: str, scenario, zenoh):
    """(recorder, tapped bus) when recording, else (None, None): the process opens its own bus."""
    if not record_dir:
        return None, None
    from autopower.recording.live import open_recorder
    from autopower.runtime.bus import ZenohBus

    recorder = open_recorder(record_dir, node, scenario=scenario)
    return recorder, recorder.tap(ZenohBus(zenoh))


def mission_options(f):
    """The mission settings `basestation` and `up` share (one definition, so they cannot drift)."""
    for option in reversed([
        click.option("--energy", multiple=True, metavar="ROBOT=J", help="Starting energy of a robot (repeatable)."),
        click.option("--energy-scale", type=float, default=None,
                     help="Multiply every starting energy, e.g. 0.01 to watch a whole mission in a minute or two."),
        click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None),
        click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None),
        click.option("--media", multiple=True, metavar="GROUP=MEDIUM",
                     help="Fix a link group's medium, e.g. laptop-robot=gsm (default: the planner chooses)."),
        click.option("--pin", multiple=True, metavar="STAGE=NODE", help="Keep a stage on a node (repeatable)."),
        click.option("--no-replan", is_flag=True,
                     help="No decisions on battery drift, periodically or when a schedule's phase ends."),
        click.option("--policy", type=click.Choice(list(POLICY_NAMES)), default="rebalance", show_default=True,
                     help="What decides the placement (the simulator's policies): static never moves by choice, "
                          "reactive replans on events, rebalance follows a time-sharing schedule, subgroup "
                          "reallocates within the parts of the team that reach each other."),
    ]):
        f = option(f)
    return f


@click.command("basestation")
@network_options
@click.option("--speed", type=float, default=DEFAULT_SPEED, show_default=True,
              help="Virtual seconds per wall second.")
@mission_options
@click.option("--replan-interval", type=float, default=600.0, show_default=True,
              help="Virtual seconds between re-plans with the remaining energies.")
@click.option("--start-grace", type=float, default=30.0, show_default=True,
              help="Wall seconds to wait for every robot before starting without the missing ones.")
def basestation(scenario_name, team, listen, connect, lease_ms, status_period, duration, parent_pid, log_level,
                record_dir, speed, energy, energy_scale, accounting, topology, media, pin, no_replan, policy,
                replan_interval, start_grace):
    """Run the base station: plan, place and migrate components; the operator's sink."""
    from autopower.agent.node import NodeRuntime
    from autopower.basestation.coordinator import CoordinatorConfig
    from autopower.basestation.process import BaseStation, BaseStationConfig

    setup_logging(log_level)
    if not speed > 0:
        raise AutoPowerError(f"--speed must be > 0, got {speed}")
    scenario = build_scenario(scenario_name, energy, energy_scale, accounting)
    media_choice = parse_pairs(media, "--media", "laptop-robot=gsm") or None
    if media_choice:
        scenario.network(topology=topology, media=media_choice)  # unknown group or medium -> ScenarioError
    coordinator = CoordinatorConfig(speed=speed, topology=topology, media=media_choice,
                                    pins=parse_pairs(pin, "--pin", "Loc-2=r1"),
                                    auto_replan=not no_replan, replan_interval_s=replan_interval,
                                    start_grace_s=start_grace, policy=policy)
    config = BaseStationConfig(scenario=scenario, team=team, zenoh=zenoh_settings(listen, connect, lease_ms),
                               coordinator=coordinator, status_period_s=status_period, parent_pid=parent_pid)
    recorder, bus = _recording_bus(record_dir, scenario.basestation, scenario, config.zenoh)
    try:
        with BaseStation(config, host_factory=NodeRuntime, bus=bus) as process:
            if recorder is not None:
                recorder.attach(process.runtime)
            reason = run_until_signalled(process, duration)
    finally:
        if bus is not None:
            bus.close()
    exit_now(f"base station stopped: {reason}")


# ---------------------------------------------------------------------------------------------
# up
# ---------------------------------------------------------------------------------------------


def summarize(snap: dict, *, team: str, speed: float, ready_after_s: float, wall_s: float,
              exit_codes: dict | None = None, log_dir: str = "") -> dict:
    """The JSON summary of a run: placement, batteries vs the model, sources, sinks, errors."""
    robots = {}
    for name, info in snap.get("robots", {}).items():
        st = info.get("status") or {}
        initial, battery, t = st.get("initial_j"), st.get("battery_j"), st.get("t_virtual") or 0.0
        consumed = (initial - battery) if initial is not None and battery is not None else None
        measured = consumed / t if consumed is not None and t > 0 else None
        predicted = info.get("predicted_w")
        robots[name] = {
            "present": info.get("present"), "departed": info.get("departed"),
            "initial_j": initial, "battery_j": battery, "consumed_j": consumed, "t_virtual": t,
            "mean_power_w": measured, "predicted_w": predicted,
            "power_error": (measured / predicted - 1) if measured and predicted else None,
            "window_power_w": sum(st.get("power_w", {}).values()) if st else None,
            "cpu_utilisation": st.get("cpu_utilisation"), "hosted": st.get("hosted", {}),
            "sources": st.get("sources", {}), "sinks": st.get("sinks", {}),
            "errors": st.get("errors", {}), "counters": st.get("counters", {}),
            "energy_by_part_j": st.get("energy_j", {}),
        }
    base = snap.get("basestation") or {}
    produced = sum(s.get("produced_total", 0) for r in robots.values() for s in r["sources"].values())
    missed = sum(s.get("missed", 0) for r in robots.values() for s in r["sources"].values())
    return {
        "team": team, "scenario": snap.get("scenario"), "accounting": snap.get("accounting"), "speed": speed,
        "policy": snap.get("policy"),
        "ready": snap.get("ready"), "ready_after_s": ready_after_s, "wall_s": wall_s,
        "t_virtual": snap.get("t_virtual"),
        "placement": snap.get("placement"), "target": snap.get("target"), "media": snap.get("media"),
        "running": snap.get("running"), "disabled": snap.get("disabled"),
        "planned_lifetime_s": snap.get("planned_lifetime_s"), "predicted_lifetime_s": snap.get("predicted_lifetime_s"),
        "reasons": snap.get("reasons"),
        "robots": robots,
        "basestation": {"sinks": base.get("sinks", {}), "errors": base.get("errors", {}),
                        "counters": base.get("counters", {}), "hosted": base.get("hosted", {}),
                        "compute_ms": base.get("compute_ms", {})},
        "frames_produced": produced, "periods_missed": missed,
        "missed_ratio": missed / (produced + missed) if produced + missed else 0.0,
        "migrations_done": snap.get("migrations_done"), "downtime_ms": snap.get("downtime_ms"),
        "replans": snap.get("replans"), "first_depletion": snap.get("first_depletion"),
        "events": snap.get("events"), "exit_codes": exit_codes or {}, "log_dir": log_dir,
    }


def render(snap: dict, speed: float):
    """The live status table of `autopower up`."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    revisit = snap.get("revisit_at_s")
    parts = [f"{snap.get('scenario')}", f"{snap.get('accounting')} accounting",
             f"t = {snap.get('t_virtual', 0):.0f} s virtual (x{speed:g})", f"policy {snap.get('policy')}",
             f"planned lifetime {snap.get('planned_lifetime_s')} s", f"media {snap.get('media')}"]
    if revisit is not None:  # a time-sharing schedule switches configuration then
        parts.append(f"next phase at t = {revisit:.0f} s")
    if not snap.get("ready"):
        parts.append("placing…")
    head = Text(" · ".join(parts), style="bold")
    robots = Table("robot", "battery", "power W (plan)", "CPU", "hosts", "sources (frames/missed)", "links",
                   title="robots", title_justify="left")
    for name, info in snap.get("robots", {}).items():
        st = info.get("status")
        if not st:
            robots.add_row(name, "joining" if info.get("present") else "absent", "", "", "", "", "")
            continue
        battery = st["battery_j"]
        pct = battery / st["initial_j"] * 100 if st["initial_j"] else 0
        power = sum(st["power_w"].values())
        plan_w = info.get("predicted_w")
        sources = ", ".join(f"{c} {s['produced_total']}/{s['missed']}" for c, s in st["sources"].items())
        links = " ".join(f"{p}{'✓' if up else '✗'}" for p, up in st["links"].items())
        robots.add_row(name, f"{battery:,.0f} J ({pct:.1f}%)" + (" DEPLETED" if st["depleted"] else ""),
                       f"{power:.3f} ({plan_w:.3f})" if plan_w else f"{power:.3f}",
                       f"{st['cpu_utilisation']:.0%}", ", ".join(st["hosted"]) or "-", sources or "-", links)
    stages = Table("stage", "runs on", "planned", "why", title="components", title_justify="left")
    for stage, want in snap.get("target", {}).items():
        have = snap.get("placement", {}).get(stage, "-")
        moving = snap.get("migrating", {}).get(stage)
        stages.add_row(stage, have + (f" → {moving['to']}" if moving else ""), want,
                       (snap.get("reasons") or {}).get(stage, ""))
    sinks = []
    base = snap.get("basestation") or {}
    for chain, s in (base.get("sinks") or {}).items():
        sinks.append(f"{chain}: {s['received_total']} results, p50 {s['latency_ms_p50']:.1f} ms")
    foot = Text("operator sink: " + ("; ".join(sinks) or "nothing yet") + "\n" +
                "\n".join((snap.get("events") or [])[-4:]), style="dim")
    return Group(head, robots, stages, foot)


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
def up(scenario_name, speed, duration, as_json, energy, energy_scale, accounting, topology, media, pin, no_replan,
       policy, lease_ms, direct_links, ready_timeout, log_dir, until_depleted, record_dir):
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
        scenario.network(topology=topology, media=parse_pairs(media, "--media", "laptop-robot=gsm"))
    spec = TeamSpec(scenario=scenario_name, speed=speed, energy=tuple(energy), energy_scale=energy_scale,
                    accounting=accounting, topology=topology, media=tuple(media), pins=tuple(pin),
                    auto_replan=not no_replan, policy=policy,
                    lease_ms=lease_ms, log_dir=log_dir, proxied_links=not direct_links,
                    record_dir=Path(record_dir) if record_dir else None)
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
                       "control": str(control.path)})
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
    summary = summarize(snap, team=team.team, speed=speed, ready_after_s=ready_after or -1.0,
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


# ---------------------------------------------------------------------------------------------
# operator commands
# ---------------------------------------------------------------------------------------------


def operator_options(f):
    f = click.option("--team", default=None, help="Team name (default: the last `autopower up`).")(f)
    f = click.option("--connect", multiple=True, metavar="ENDPOINT",
                     help="The base station's endpoint (default: the last `autopower up`).")(f)
    f = click.option("--timeout", type=float, default=5.0, show_default=True)(f)
    return f


def _client(team: str | None, connect: tuple[str, ...]):
    from autopower.basestation.operator import OperatorClient, read_session

    if not team or not connect:
        session = read_session()
        team = team or session["team"]
        connect = connect or tuple(session["connect"])
    return OperatorClient(team, connect=connect)


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
    if as_json:
        click.echo(json.dumps(snap, indent=2, default=str))
    else:
        from rich.console import Console

        Console().print(render(snap, (snap.get("mission") or {}).get("speed", 1.0)))


from autopower.cli.demo import demo  # noqa: E402  (after the commands they sit beside)
from autopower.launch.faults import fault  # noqa: E402

COMMANDS = (agent, basestation, up, chain, migrate, status, fault, demo)


@click.group()
def runtime() -> None:
    """AutoPower runtime commands (normally reached through `autopower`)."""


for _command in COMMANDS:
    runtime.add_command(_command)


def main() -> None:
    """``python -m autopower.cli.team ...``: how `up` starts its children."""
    from autopower.cli.entry import run_command

    run_command(runtime)


if __name__ == "__main__":
    main()
