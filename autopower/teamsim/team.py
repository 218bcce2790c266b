"""A whole team in one process, on simulated time and a simulated network, judged by the oracle.

`run` builds the `World` of one run (the event queue, the network, the trace, the oracle's
ledger, the stores' folder), starts the base station and every robot at time 0, carries out the
fault schedule over the mission, lets everything heal in the quiet phase, and then judges:

- exactly once: every output produced before the judging horizon (the end less `DRAIN_S`) was
  delivered once, or is in the budget (`oracle.Ledger`); a second delivery is a violation;
- outputs: each delivered output is what its chain computes from that seq's input (stand-ins);
- sources: no source produces two frames under one (chain, run, seq);
- sequencing: no stage saw an input skipped or repeated (a stand-in stage fails on one);
- energy: each robot's metered parts add up to what its battery lost, and its idle CPU part is
  its platform's idle power over the whole mission, restarts included;
- one leader: at most one base station leads (has a mission and has not stepped down) at a time;
- the newest plan: after the quiet phase (and once no plan is on its way, `SETTLE_S`) every node
  runs the base station's newest plan, every stage runs where the plan puts it (its host runs it),
  and every chain the operator left enabled runs;
- no internal error: no exception escaped a core.
"""

from __future__ import annotations

import dataclasses
import math
import os
import random
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.parts import CPU_IDLE
from autopower.model.scenario import Scenario
from autopower.node.stages import Lifecycle
from autopower.protocol import Keys, NodeStatus
from autopower.protocol.access import TeamAccess
from autopower.runtime.clock import VirtualClock
from autopower.teamsim import components
from autopower.teamsim.evidence import only_in
from autopower.teamsim.faults import Fault
from autopower.teamsim.inject import Injector
from autopower.teamsim.network import LEASE_S, SimNetwork
from autopower.teamsim.oracle import ChainCounts, Ledger, Violation
from autopower.teamsim.scheduler import Scheduler
from autopower.teamsim.shells import BaseShell, RobotShell, Shell
from autopower.teamsim.trace import Trace

DRAIN_S = 10.0  # outputs produced in the last seconds of a run are still on their way: not judged
SETTLE_S = 2.0  # the run is judged once the newest plan is this old and no migration is under way...
SETTLE_MAX_S = 30.0  # ... or this long after the quiet phase, whichever comes first
STATUS_PERIOD_S = 0.5
STATUS_REST_PERIOD_S = 2.0  # the slow heartbeat (`AgentConfig.status_rest_period_s`)
# How long a robot's model may price a stage it does not run (`World._model_runs`): a reconfiguration
# (a round's state on its way, a restarted robot's first plan, a plan waiting for a robot's answer)
# takes a few status periods; a stage left starting for good lasted as long as the partition (280 s).
UNRUN_GRACE_S = 10.0
_RUNS = (Lifecycle.RUNNING, Lifecycle.DRAINING, Lifecycle.MIGRATED)  # running, or handing over to its next host
STATUS_WINDOW_S = 2.0
ENERGY_TOLERANCE = 1e-6  # relative


@dataclass(frozen=True)
class SimConfig:
    scenario: Scenario
    seed: int
    faults: tuple[Fault, ...] = ()
    mission_s: float = 120.0  # faults happen in [WARMUP_S, mission_s)
    quiet_s: float = 40.0  # then nothing but healing
    components: str = "stand-in"  # or "real"
    speed: float = 1.0  # mission seconds per simulated second: 1 keeps each radio's real rate
    policy: str = "rebalance"
    subgroup: bool = True  # robots cut off from the base station reallocate among themselves (`SubgroupRounds`)
    keep_trace: bool = False

    @property
    def end_s(self) -> float:
        return self.mission_s + self.quiet_s


@dataclass
class SimResult:
    seed: int
    trace_sha256: str
    violations: list[Violation]
    faults: list[Fault]
    chains: dict[str, ChainCounts]
    wall_s: float
    virtual_s: float
    events: int
    network: dict = field(default_factory=dict)
    trace: list[str] | None = None
    robots: int = 0
    # the base station's policy over every incarnation: {"count", "seconds", "max_s"} (wall), and its
    # answers not proven optimal: "not_proven" (how many), "not_proven_max_gap" (the largest MILP gap known)
    decisions: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations

    def traffic(self) -> dict:
        """Messages and bytes sent per robot per simulated second, the chains' data (frames, routed
        packets, migrated state) apart from the control plane (statuses, plans, orders, votes, ...)."""
        per = max(self.robots, 1) * max(self.virtual_s, 1e-9)
        out = {"data": [0, 0], "control": [0, 0]}
        for kind, (count, size) in self.network.get("by_kind", {}).items():
            side = out["data" if kind.rpartition(":")[2] in DATA_KINDS else "control"]  # "relayed:packet": data
            side[0] += count
            side[1] += size
        return {side: {"messages": round(n / per, 3), "bytes": round(b / per, 1)} for side, (n, b) in out.items()}

    def to_json(self) -> dict:
        return {"seed": self.seed, "trace_sha256": self.trace_sha256, "ok": self.ok,
                "violations": [v.to_json() for v in self.violations],
                "faults": [f.to_json() for f in self.faults],
                "chains": {name: c.to_json() for name, c in self.chains.items()},
                "wall_s": round(self.wall_s, 3), "virtual_s": round(self.virtual_s, 3), "events": self.events,
                "network": dict(self.network), "robots": self.robots, "decisions": dict(self.decisions),
                "per_robot_per_s": self.traffic()}


DATA_KINDS = frozenset({"frame", "packet", "state"})  # message kinds that carry the chains' data


class World:
    """What every shell of one run shares, and what happens to whole processes."""

    def __init__(self, config: SimConfig, store_dir: Path):
        self.config = config
        self.scenario = config.scenario
        self.seed = config.seed
        self.scheduler = Scheduler()
        self.trace = Trace(keep=config.keep_trace)
        self.network = SimNetwork(self.scenario, self.scheduler, random.Random(config.seed))
        self.keys = Keys("sim")
        self.access = TeamAccess(self.keys, self.scenario.basestation, tuple(r.name for r in self.scenario.robots))
        self.ledger = Ledger([c.name for c in self.scenario.chains])
        self.store_dir = store_dir
        self.status_period_s = STATUS_PERIOD_S
        self.status_rest_period_s = STATUS_REST_PERIOD_S
        self.subgroup = config.subgroup
        self.status_window_s = STATUS_WINDOW_S
        self.coordinator_config = CoordinatorConfig(speed=config.speed, policy=config.policy,
                                                    learn_team_s=2 * STATUS_PERIOD_S + LEASE_S)
        if config.components == "stand-in":
            self.make_component, self.make_source = components.StandInComponent, components.StandInSource
        else:
            from autopower import chains

            self.make_component, self.make_source = chains.make_component, chains.make_source
        self._expected = {c.name: c for c in self.scenario.chains
                          if config.components == "stand-in" and not c.inputs and c.sourced}
        self.base_state: dict = {}  # what the base station's state directory keeps (its incarnation)
        self.shells: dict[str, Shell] = {}
        self.base_shells: list[BaseShell] = []  # every start of the base station, for its decisions
        self.base_starts = 0
        self.process_starts = 0  # every process started, for its id (`NodeStatus.process`): the same each run
        self.failed_seen: set[tuple[str, str]] = set()
        self.idle_from: dict[str, float] = {}  # robot -> virtual time its metering began
        # (robot's process, stage) -> since when its model prices the stage there while it does not run it
        self.unrun_since: dict[tuple[Shell, str], float] = {}

    def decisions(self) -> dict:
        """How often the base station's policy decided, over all its starts, and the wall time it took."""
        parts = [shell.co.deciding for shell in self.base_shells if shell.co is not None]
        gaps = [d.decider.unproven_max_gap for d in parts if d.decider.unproven_max_gap is not None]
        return {"count": sum(d.decisions for d in parts), "seconds": round(sum(d.decide_s for d in parts), 4),
                "max_s": round(max((d.decide_max_s for d in parts), default=0.0), 4),
                "not_proven": sum(d.decider.unproven for d in parts),
                "not_proven_max_gap": round(max(gaps), 6) if gaps else None}

    def clock_for(self, mission) -> VirtualClock:
        return VirtualClock(mission.epoch_unix, mission.speed, wall_fn=self.scheduler.wall)

    def expected(self, chain: str, seq: int) -> bytes | None:
        spec = self._expected.get(chain)
        return components.expected_output(spec, seq) if spec is not None else None

    # ---- processes ------------------------------------------------------------------------------
    def start(self, node: str) -> None:
        if node == self.scenario.basestation:
            shell: Shell = BaseShell(self, node, self.base_starts)
            self.base_shells.append(shell)
            self.base_starts += 1
        else:
            shell = RobotShell(self, node)
        self.shells[node] = shell
        self.trace.note(self.scheduler.now, f"start {node}")
        shell.start()

    def is_up(self, node: str) -> bool:
        shell = self.shells.get(node)
        return shell is not None and shell.up

    def crash(self, node: str) -> None:
        self.trace.note(self.scheduler.now, f"crash {node}")
        if self.is_up(node):  # what dies with it: the evidence a "died with the process" label needs
            self.ledger.killed_with(only_in(self, node))
        self.shells[node].crash()

    def restart(self, node: str) -> None:
        if not self.is_up(node):
            self.start(node)

    def freeze(self, node: str) -> None:
        self.shells[node].freeze()

    def thaw(self, node: str) -> None:
        if self.is_up(node):
            self.shells[node].thaw()

    def operator(self, cmd):
        shell = self.shells.get(self.scenario.basestation)
        reply = shell.operator(cmd) if isinstance(shell, BaseShell) else None
        self.trace.note(self.scheduler.now, f"operator {type(cmd).__name__} {dataclasses.asdict(cmd)}: "
                        f"{'failed' if reply is None else ('ok' if reply.ok else 'refused')}")
        return reply

    def stepped_down(self, shell: BaseShell) -> None:
        self.trace.note(self.scheduler.now, f"{shell.node} stepped down: {shell.co.takeover.stepped_down}")
        shell.crash()

    def close(self) -> None:
        """Every process still up stops as a kill would: its stores' files closed (a sweep runs
        thousands of teams in one process: each left 17 journals open, and a worker ran out of files)."""
        for shell in self.shells.values():
            shell.crash()

    # ---- what the oracle watches as the run goes -------------------------------------------------------
    def internal_error(self, node: str, exc: Exception) -> None:
        self.ledger.violate("no-internal-error", f"{node}: {type(exc).__name__}: {exc}", self.scheduler.now,
                            self.trace.events)

    def status_sent(self, shell: Shell, status: NodeStatus) -> None:
        for stage, why in sorted(status.failed.items()):
            if (shell.node, stage) not in self.failed_seen:
                self.failed_seen.add((shell.node, stage))
                self.ledger.violate("sequencing", f"{stage} stopped on {shell.node}: {why}", self.scheduler.now,
                                    self.trace.events)
        rt = shell.rt
        if rt.meter is not None and not rt.resuming.resumed and shell.node != self.scenario.basestation:
            self.idle_from[shell.node] = rt.meter.t0
        if shell.node != self.scenario.basestation:
            self._model_runs(shell)
        leaders = [s.node for s in self.base_shells if self.shells.get(s.node) is s
                   and s.up and s.co.mission is not None and s.co.takeover.stepped_down is None]
        if len(leaders) > 1:
            self.ledger.violate("one-leader", f"{len(leaders)} base stations lead at once", self.scheduler.now,
                                self.trace.events)

    def _model_runs(self, shell: Shell) -> None:
        """A robot's model prices only what it runs, give or take a reconfiguration: a stage its plan
        puts on it (`PlanView.priced_here`) that it has not run for `UNRUN_GRACE_S` is work the model
        charges and nobody does (a chain standing still while the team believes it runs)."""
        rt, now = shell.rt, self.scheduler.now
        hosted = {s: h.lifecycle for s, h in rt.hosted.items()}
        unrun = {s for s in rt.plan_view.priced_here() if hosted.get(s) not in _RUNS}
        for key in [k for k in self.unrun_since if k[0] is shell and k[1] not in unrun]:
            del self.unrun_since[key]
        for stage in sorted(unrun):
            since = self.unrun_since.setdefault((shell, stage), now)
            if now - since > UNRUN_GRACE_S and since >= 0:
                self.unrun_since[(shell, stage)] = -1.0  # said once
                state = hosted[stage].value if stage in hosted else "not hosted"
                self.ledger.violate("model-runs", f"{shell.node}'s model prices {stage} there since t={since:.1f} s, "
                                    f"but it is {state} there", now, self.trace.events)

    # ---- after the run ----------------------------------------------------------------------------------
    def settled(self) -> bool:
        """No plan is on its way (none waits for a robot it changes nothing for, `PlanDelivery`)
        and nothing migrates (the team may be judged on its newest plan)."""
        base = self.shells.get(self.scenario.basestation)
        if not (isinstance(base, BaseShell) and base.up and base.co.mission is not None):
            return True
        co = base.co
        since = base.plan_since.get((co.takeover.incarnation, co.plans.epoch), -math.inf)
        return not co.placing.migrations and not co.plans.delivery.lagging and self.scheduler.now - since >= SETTLE_S

    def final_checks(self) -> None:
        now, event = self.scheduler.now, self.trace.events
        for shell in self.shells.values():
            if shell.up:
                shell.commit_outputs()  # alive at the end: its next status commits them
        self._duplicates_carried(now, event)
        base = self.shells.get(self.scenario.basestation)
        if not (isinstance(base, BaseShell) and base.up and base.co.mission is not None):
            self.ledger.violate("newest-plan", "no base station runs the mission at the end", now, event)
            return
        co = base.co
        newest = (co.takeover.incarnation, co.plans.epoch)
        for node, shell in sorted(self.shells.items()):
            if not shell.up:
                self.ledger.violate("newest-plan", f"{node} is down at the end", now, event)
            elif shell.rt.plan_view.order != newest:
                self.ledger.violate("newest-plan", f"{node} runs plan {shell.rt.plan_view.order}, the base station's "
                                    f"newest is {newest}", now, event)
        if not co.ready:
            placement = co.placing.placement
            waiting = {s: (placement.get(s), n) for s, n in sorted(co.placing.target.items()) if placement.get(s) != n}
            self.ledger.violate("newest-plan", f"not every stage runs where the plan wants it (stage: (runs, wanted) "
                                f"{waiting}; migrating {sorted(co.placing.migrations)})", now, event)
        for stage, node in sorted(co.placing.placement.items()):
            shell = self.shells.get(node)
            hosted = shell.rt.hosted.get(stage) if shell is not None and shell.up else None
            if hosted is None or hosted.lifecycle is not Lifecycle.RUNNING:
                self.ledger.violate("newest-plan", f"the plan runs {stage} on {node}, which "
                                    f"{'does not host it' if hosted is None else 'hosts it ' + hosted.lifecycle.value}",
                                    now, event)
        disabled, running = co.operating.disabled, co.placing.runs.running
        idle = sorted(c.name for c in self.scenario.chains if c.name not in disabled and c.name not in running)
        if idle:
            self.ledger.violate("newest-plan", f"enabled chains not running at the end: {', '.join(idle)}", now, event)
        for node, shell in sorted(self.shells.items()):
            if node != self.scenario.basestation and shell.up and shell.rt.meter is not None:
                self._energy(node, shell)

    def _duplicates_carried(self, now: float, event: int) -> None:
        """A sink hands each output on once (`Frames._sink`), so the oracle's deliveries cannot show an
        output produced twice; the sink's count of second copies can. Each must be a copy the network
        made (a duplicating link), not one the team produced."""
        for node, shell in sorted(self.shells.items()):
            if not shell.up:
                continue
            counted = sum(ledger.duplicates_total for _, ledger in sorted(shell.rt.sinks.items()))
            carried = sum(self.network.copies_arrived.get((node, key), 0)
                          for key in (self.keys.node_data(node), self.keys.node_relay(node)))
            if counted > carried:
                self.ledger.violate("exactly-once", f"{node}'s sinks counted {counted} second copies of outputs, "
                                    f"the network duplicated {carried} message(s) to it: an output was produced "
                                    "twice", now, event)

    def _energy(self, robot: str, shell: Shell) -> None:
        rt = shell.rt
        rt.metering.settle_relayed()
        meter = rt.meter
        meter.advance(rt.now())
        now, event = self.scheduler.now, self.trace.events
        parts = math.fsum(v for _, v in sorted(meter.energy_j.items()))
        lost = meter.initial_j - meter.battery_j
        if not math.isclose(parts, lost, rel_tol=ENERGY_TOLERANCE, abs_tol=1e-6):
            self.ledger.violate("energy", f"{robot}: parts add up to {parts!r} J, its battery lost {lost!r} J",
                                now, event)
        platform = self.scenario.platform_of(robot)
        if not platform.levels and robot in self.idle_from:
            want = platform.idle_w * (meter.t - self.idle_from[robot])
            got = meter.energy_j.get(CPU_IDLE, 0.0)
            if not math.isclose(got, want, rel_tol=ENERGY_TOLERANCE, abs_tol=1e-6):
                self.ledger.violate("energy", f"{robot}: idle CPU {got!r} J, its platform's idle power over the "
                                    f"mission is {want!r} J", now, event)


def run(config: SimConfig, store_dir: Path | None = None) -> SimResult:
    """One simulated run of ``config`` (its stores in ``store_dir``, or a temporary folder)."""
    started = time.perf_counter()
    if store_dir is None:
        with tempfile.TemporaryDirectory(prefix="autopower-sim-", dir=_memory_folder()) as folder:
            return _run(config, Path(folder), started)
    return _run(config, store_dir, started)


def _memory_folder() -> str | None:
    """A folder in memory for the stores when the machine has one (a file replaced per status costs
    half a millisecond on a disk); else the system's temporary folder."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def _run(config: SimConfig, store_dir: Path, started: float) -> SimResult:
    world = World(config, store_dir)
    try:
        return _judged(config, world, started)
    finally:
        world.close()


def _judged(config: SimConfig, world: World, started: float) -> SimResult:
    world.start(config.scenario.basestation)
    for robot in sorted(r.name for r in config.scenario.robots):
        world.start(robot)
    Injector(world, list(config.faults))
    world.scheduler.run_until(config.end_s)
    while not world.settled() and world.scheduler.now < config.end_s + SETTLE_MAX_S:
        world.scheduler.run_until(world.scheduler.now + 0.5)
    world.final_checks()
    chains = world.ledger.verdict(config.end_s - DRAIN_S)
    violations = sorted(world.ledger.violations, key=lambda v: (v.event, v.invariant))
    base = world.shells.get(config.scenario.basestation)
    virtual_s = base.co.now() if isinstance(base, BaseShell) and base.up else 0.0
    return SimResult(seed=config.seed, trace_sha256=world.trace.sha256, violations=violations,
                     faults=list(config.faults), chains=chains, wall_s=time.perf_counter() - started,
                     virtual_s=virtual_s, events=world.trace.events,
                     network=dataclasses.asdict(world.network.stats), trace=world.trace.lines,
                     robots=len(config.scenario.robots), decisions=world.decisions())
