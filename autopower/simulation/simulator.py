"""A discrete-event mission simulator in virtual time, driven by the same policies as the base station.

Between two instants where something happens, every robot's power is constant (the energy model
is a steady-state model), so the simulator jumps from instant to instant and drains batteries
exactly: ``E_i -= P_i * dt``. The instants are the events of an events file
(`autopower.runtime.events`), the times a policy asked to be consulted again (``revisit_at_s``) and the
moment the first robot runs dry, which ends the mission. A robot that has left the team is not
metered.

At every instant the policy gets a `autopower.policies.TeamState` (battery readings optionally
noisy, seeded) and may return a `Decision`; the simulator charges its migrations as they would
really cost (state bytes over the radios crossed, CPU on both hosts, missed periods) and switches
configuration. Everything is a function of (scenario, events, policy, seed): the same inputs give
the same result, bit for bit.

Entry points: `simulate(...)` returns a `SimulationResult`; `time_sharing_reference(...)` the
planner's upper bound for an event-free mission, to compare against.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.dvfs import cpu_at_best_levels, has_levels
from autopower.model.energy import LoadSpace, active_chains, load_of
from autopower.model.mission_events import NO_EVENTS, EventScript, MissionEvent
from autopower.model.network import Network, media_choices
from autopower.model.scenario import Scenario
from autopower.model.variants import apply_variants
from autopower.planner.plan_choices import mission_variants
from autopower.planner.problem import PlanRequest, make_problem
from autopower.policies import (
    Decision,
    MigrationCosts,
    Move,
    Policy,
    SchedulePhase,
    TeamState,
    base_media,
    derive_network,
    effective_scenario,
    make_policy,
    plan_moves,
)

DEFAULT_HORIZON_S = 10 * 365 * 86400.0  # a mission where nobody runs dry stops here
MAX_DECISIONS = 100_000


@dataclass(frozen=True, kw_only=True)
class MigrationRecord:
    time_s: float
    move: Move

    def to_dict(self) -> dict:
        return {"time_s": self.time_s, **self.move.to_dict()}


@dataclass(frozen=True, kw_only=True)
class DecisionRecord:
    time_s: float
    forced: bool
    moves: int
    started: tuple[str, ...]
    stopped: tuple[str, ...]
    media: Mapping[str, str]
    allocation: Mapping[str, str]
    reasons: tuple[str, ...]
    predicted_lifetime_s: float | None  # remaining, from time_s
    predicted_gain_s: float | None

    def to_dict(self) -> dict:
        return {"time_s": self.time_s, "forced": self.forced, "moves": self.moves, "started": list(self.started),
                "stopped": list(self.stopped), "media": dict(self.media), "allocation": dict(self.allocation),
                "reasons": list(self.reasons), "predicted_lifetime_s": self.predicted_lifetime_s,
                "predicted_gain_s": self.predicted_gain_s}


@dataclass(frozen=True, kw_only=True)
class Segment:
    """An interval with one configuration and constant power."""

    start_s: float
    end_s: float
    media: Mapping[str, str]
    allocation: Mapping[str, str]
    power_w: Mapping[str, float]


@dataclass
class SimulationResult:
    scenario: str
    policy: str
    seed: int
    accounting: str
    topology: str
    lifetime_s: float  # mission time when it ended
    end_reason: str
    first_dry: str | None  # the robot that ran dry first (None if the mission ended otherwise)
    initial_energies_j: dict[str, float]
    final_energies_j: dict[str, float]
    decisions: list[DecisionRecord] = field(default_factory=list)
    migrations: list[MigrationRecord] = field(default_factory=list)
    events: list[tuple[float, str]] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)
    wall_s: float = 0.0  # not part of the result proper (varies run to run)

    @property
    def migration_energy_j(self) -> float:
        return float(sum(sum(m.move.energy_j.values()) for m in self.migrations))

    @property
    def missed_periods(self) -> int:
        return int(sum(m.move.missed_periods for m in self.migrations))

    @property
    def downtime_s(self) -> float:
        return float(sum(m.move.downtime_s for m in self.migrations))

    def to_dict(self, *, segments: bool = False) -> dict:
        out = {
            "scenario": self.scenario, "policy": self.policy, "seed": self.seed, "accounting": self.accounting,
            "topology": self.topology, "lifetime_s": self.lifetime_s, "end_reason": self.end_reason,
            "first_dry": self.first_dry, "initial_energies_j": self.initial_energies_j,
            "final_energies_j": self.final_energies_j, "migrations": len(self.migrations),
            "migration_energy_j": self.migration_energy_j, "missed_periods": self.missed_periods,
            "migration_downtime_s": self.downtime_s,
            "decisions": [d.to_dict() for d in self.decisions],
            "migration_log": [m.to_dict() for m in self.migrations],
            "events": [{"time_s": t, "what": what} for t, what in self.events],
        }
        if segments:
            out["segments"] = [dataclasses.asdict(s) for s in self.segments]
        return out


def time_sharing_reference(scenario: Scenario, *, topology: str | None = None, accounting: str | None = None):
    """The planner's time-sharing bound for the mission without events (migrations free)."""
    from autopower.planner import plan
    from autopower.planner.timesharing import time_sharing_bound

    request = PlanRequest(scenario=scenario, topology=topology, accounting=accounting)
    best = plan(request)
    return time_sharing_bound(make_problem(request), [(best.network, best.allocation)]), best


class _Mission:
    def __init__(self, scenario: Scenario, events: EventScript, policy: Policy, seed: int, topology: str | None,
                 accounting: str | None, telemetry, horizon_s: float):
        self.raw = scenario
        self.script = events
        self.policy = policy
        self.seed = seed
        self.topology = topology or scenario.network_spec.topology
        self.accounting = accounting or scenario.accounting
        self.telemetry = telemetry
        self.horizon_s = horizon_s
        self.rng = np.random.default_rng(seed)
        self.migration = MigrationCosts.from_scenario(scenario, events.migration)
        self.t = 0.0
        self.energy = {r.name: float(r.energy_j) for r in scenario.robots}
        self.away = set(events.initially_absent)
        self.cuts: set[frozenset[str]] = set()
        self.faults: dict[str, tuple[str | None, str | None]] = {}
        self.disabled: set[str] = set()
        self.media = dict(media_choices(scenario, self.topology)[0])
        self.allocation: dict[str, str] = {}
        self.schedule: tuple[SchedulePhase, ...] = ()
        self.revisit: float | None = None
        self.pending: list[MissionEvent] = []
        self.queue = list(events.events)
        self.network = self.derive()
        self.result = SimulationResult(
            scenario=scenario.name, policy=getattr(policy, "name", type(policy).__name__), seed=seed,
            accounting=self.accounting, topology=self.topology, lifetime_s=0.0, end_reason="", first_dry=None,
            initial_energies_j=dict(self.energy), final_energies_j={})
        self._power_cache: tuple | None = None

    # ---- the world --------------------------------------------------------------------------------
    def derive(self) -> Network:
        return derive_network(self.raw, self.topology, self.media, frozenset(self.cuts), dict(self.faults),
                              frozenset(self.away))

    def present(self) -> list[str]:
        return [r.name for r in self.raw.robots if r.name not in self.away]

    def power(self) -> dict[str, float]:
        """Watts per present robot for the current configuration (the model's steady state)."""
        key = (self.network, tuple(sorted(self.allocation.items())), frozenset(self.disabled))
        if self._power_cache and self._power_cache[0] == key:
            return self._power_cache[1]
        scenario, _ = effective_scenario(self.raw, self.network)
        space = LoadSpace(scenario, self.network, self.accounting, {r: max(self.energy[r], 1e-9)
                                                                     for r in self.present()})
        chains = [c for c in active_chains(scenario, self.network, frozenset(self.disabled))
                  if all(s.name in self.allocation for s in c.stages)]
        load = load_of(space, chains, self.allocation)[None, :]
        if not space.feasible(load)[0]:
            raise AutoPowerError(f"internal error: the configuration at {self.t:.1f} s exceeds a CPU or radio "
                                 f"limit; the policy {self.result.policy} should not have chosen it")
        watts = dict(zip(space.robots, map(float, space.total_power(load)[0]), strict=False))
        parts = space.breakdown(load)
        if has_levels(scenario):  # DVFS: every robot at its cheapest level that fits (model.dvfs)
            cpu_w, _ = cpu_at_best_levels(space, parts)
            watts = {r: w - float(parts["cpu_w"][0, i]) + float(cpu_w[0, i]) for i, (r, w) in enumerate(watts.items())}
            parts = {**parts, "cpu_w": cpu_w}
        self._parts = {robot: {"cpu": float(parts["cpu_w"][0, i]),
                               **{f"{m}/{kind}": float(parts[f"{kind}_w"][0, i, j])
                                  for j, m in enumerate(space.media) if space.present[i, j]
                                  for kind in ("send", "receive", "sleep")}}
                       for i, robot in enumerate(space.robots)}
        self._power_cache = (key, watts)
        return watts

    def state(self) -> TeamState:
        seen = {}
        for robot in self.present():
            noise = self.script.battery_noise
            factor = 1.0 + noise * float(self.rng.standard_normal()) if noise else 1.0
            seen[robot] = max(self.energy[robot] * factor, 1e-6)
        return TeamState(scenario=self.raw, time_s=self.t, network=self.network, allocation=dict(self.allocation),
                         energies_j=seen, disabled_chains=frozenset(self.disabled),
                         unavailable_nodes=frozenset(self.away), topology=self.topology,
                         cut_links=frozenset(self.cuts), radio_faults=dict(self.faults),
                         accounting=self.accounting, events=tuple(self.pending), migration=self.migration,
                         schedule=self.schedule)

    # ---- events --------------------------------------------------------------------------------------
    def apply_event(self, ev: MissionEvent) -> str | None:
        """Change the world; returns the robot that ran dry because of it, if any."""
        if ev.kind == "link-cut":
            self.cuts.add(ev.link)
        elif ev.kind == "link-heal":
            self.cuts.discard(ev.link)
        elif ev.kind == "radio-fault":
            self.faults[ev.robot] = (ev.laptop_robot, ev.robot_robot)
        elif ev.kind == "radio-repair":
            self.faults.pop(ev.robot, None)
        elif ev.kind == "chain-disable":
            self.disabled.update(ev.chains)
        elif ev.kind == "chain-enable":
            self.disabled.difference_update(ev.chains)
        elif ev.kind == "robot-leave":
            self.away.add(ev.robot)
        elif ev.kind == "robot-join":
            self.away.discard(ev.robot)
        elif ev.kind == "energy-offset":
            self.energy[ev.robot] = self.energy[ev.robot] + ev.delta_j
        self.network = self.derive()
        self.pending.append(ev)
        self.result.events.append((self.t, ev.describe()))
        self._log_text("events/faults", f"{ev.describe()}", "WARN")
        if ev.kind == "energy-offset" and ev.robot not in self.away and self.energy[ev.robot] <= 0:
            return ev.robot
        return None

    # ---- decisions -----------------------------------------------------------------------------------
    def decide(self) -> str | None:
        """Ask the policy; apply its decision. Returns the robot a migration drained, if any."""
        try:
            decision = self.policy.decide(self.state())
        except InfeasibleError as exc:
            raise _MissionOver(f"no feasible allocation: {exc}") from None
        self.pending = []
        if decision is None:
            self.revisit = None
            self.schedule = ()
            return None
        return self.apply(decision)

    def apply(self, decision: Decision) -> str | None:
        network = decision.network
        media = base_media(network)
        if media:
            self.media.update(media)
        derived = self.derive()
        if derived != network:
            raise AutoPowerError(f"internal error: policy {self.result.policy} chose a network the team cannot "
                                 f"have at {self.t:.1f} s ({network.describe()} vs {derived.describe()})")
        self.network = derived
        moves = plan_moves(effective_scenario(self.raw, self.network)[0], self.network, self.allocation,
                           decision.allocation, self.migration)
        self.allocation = dict(decision.allocation)
        self.schedule = tuple(decision.schedule)
        self.revisit = decision.revisit_at_s if (decision.revisit_at_s is not None
                                                 and decision.revisit_at_s > self.t + 1e-6) else None
        dry = None
        for move in moves:
            self.result.migrations.append(MigrationRecord(time_s=self.t, move=move))
            for robot, joules in move.energy_j.items():
                self.energy[robot] -= joules
                if self.energy[robot] <= 0 and dry is None:
                    dry = robot
            self._log_text("events/migrations", move.describe(), "INFO")
        if decision.changes_anything or decision.reasons:
            record = DecisionRecord(
                time_s=self.t, forced=decision.forced, moves=len(moves), started=tuple(decision.started),
                stopped=tuple(decision.stopped), media=network.media_by_group(), allocation=dict(self.allocation),
                reasons=tuple(decision.reasons),
                predicted_lifetime_s=_finite(decision.predicted_lifetime_s),
                predicted_gain_s=_finite(decision.predicted_gain_s))
            self.result.decisions.append(record)
            for line in decision.reasons:
                self._log_text("events/decisions", line, "INFO")
            if self.telemetry is not None:
                self.telemetry.allocation(self.t, self.allocation, list(self.network.nodes))
                self.telemetry.network(self.t, self.network, self.raw.link_specs(self.topology))
        return dry

    def _log_text(self, entity: str, text: str, level: str) -> None:
        if self.telemetry is not None:
            self.telemetry.text(entity, self.t, text, level)

    # ---- the loop ------------------------------------------------------------------------------------
    def run(self) -> SimulationResult:
        started = time.perf_counter()
        try:
            self._loop()
        except _MissionOver as over:
            self.result.end_reason = str(over)
        self.result.lifetime_s = self.t
        self.result.final_energies_j = {r: max(e, 0.0) for r, e in self.energy.items()}
        self.result.wall_s = time.perf_counter() - started
        if self.telemetry is not None:
            self._log_text("events/decisions", f"mission over at {self.t:.1f} s: {self.result.end_reason}", "INFO")
            self.telemetry.flush()
        return self.result

    def _loop(self) -> None:
        # events at t = 0 shape the world before the first plan
        while self.queue and self.queue[0].at_s <= 0.0:
            self.apply_event(self.queue.pop(0))
        if not self.present():
            raise _MissionOver("no robot in the team")
        dry = self.decide()
        decisions = 1
        while True:
            if dry is not None:
                self.result.first_dry = dry
                raise _MissionOver(f"{dry} ran dry (migration energy)")
            watts = self.power()
            self._sample()
            robots = [r for r in self.present() if watts.get(r, 0.0) > 0]
            if not robots:
                raise _MissionOver("no robot in the team")
            life = {r: self.energy[r] / watts[r] for r in robots}
            first = min(robots, key=lambda r: (life[r], r))
            t_dry = self.t + life[first]
            t_event = self.queue[0].at_s if self.queue else math.inf
            t_revisit = self.revisit if self.revisit is not None else math.inf
            t_next = min(t_dry, t_event, t_revisit, self.horizon_s)
            dt = t_next - self.t
            for r in self.present():
                self.energy[r] -= watts.get(r, 0.0) * dt
            self.result.segments.append(Segment(start_s=self.t, end_s=t_next, media=self.network.media_by_group(),
                                                allocation=dict(self.allocation), power_w=dict(watts)))
            self.t = t_next
            if t_dry <= t_next:
                self.energy[first] = 0.0
                self._sample()
                self.result.first_dry = first
                raise _MissionOver(f"{first} ran dry")
            self._sample()
            if t_next >= self.horizon_s:
                raise _MissionOver("horizon reached with every robot alive")
            while self.queue and self.queue[0].at_s <= self.t:
                dry = self.apply_event(self.queue.pop(0)) or dry
            if dry is not None:
                self.result.first_dry = dry
                raise _MissionOver(f"{dry} ran dry (energy offset)")
            if not self.present():
                raise _MissionOver("every robot has left the team")
            if t_revisit <= self.t:
                self.revisit = None
            decisions += 1
            if decisions > MAX_DECISIONS:
                raise AutoPowerError(f"internal error: more than {MAX_DECISIONS} decisions; the policy "
                                     f"{self.result.policy} keeps asking to be revisited")
            dry = self.decide()

    def _sample(self) -> None:
        if self.telemetry is None:
            return
        watts = self.power()
        for robot in self.present():
            self.telemetry.battery(self.t, robot, max(self.energy[robot], 0.0))
            # the model's prediction from here if nothing changed (the sink skips repeats)
            self.telemetry.prediction(self.t, robot, max(self.energy[robot], 0.0), watts.get(robot, 0.0))
            self.telemetry.power(self.t, robot, {"total": watts.get(robot, 0.0), **self._parts.get(robot, {})})


class _MissionOver(Exception):
    pass


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def simulate(scenario: Scenario, events: EventScript = NO_EVENTS, *, policy: str | Policy = "rebalance",
             seed: int = 0, topology: str | None = None, accounting: str | None = None, telemetry=None,
             horizon_s: float = DEFAULT_HORIZON_S, policy_params: Mapping | None = None) -> SimulationResult:
    """Run one mission until the first robot runs dry; deterministic in (inputs, seed).

    `telemetry` is an `autopower.recording.telemetry.Telemetry` (or None); logging failures never stop the run.
    """
    if isinstance(policy, str):
        policy = make_policy(policy, **dict(policy_params or {}))
    scenario = scenario.with_accounting(accounting)
    # quality variants are fixed for the mission, as a live base station fixes them (the planner's)
    scenario = apply_variants(scenario, mission_variants(scenario))
    mission = _Mission(scenario, events, policy, seed, topology, accounting, telemetry, horizon_s)
    return mission.run()
