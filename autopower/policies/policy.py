"""Dynamic reallocation policies: when to move which component where, as pure functions.

The simulator (`autopower.simulation.simulator`) and the live base station call the same code: build a
`TeamState` from what they know, call ``policy.decide(state)``, carry out the `Decision`.
Nothing here reads a clock, a socket or a file; time is ``state.time_s``, and everything a policy
must remember between calls travels in the state (``schedule``), so a restarted base station
resumes where it was.

Policies (`make_policy(name)`):

- ``static``: the best fixed plan. It never moves a component by choice; when an event makes its
  plan impossible it falls back to running the affected stages locally, then to the paper's
  all-local configuration, and only if even that fails to the optimum.
- ``reactive``: replans on events only (and when the plan cannot continue); keeps the current
  plan unless the new one lives longer *after paying the migration*.
- ``rebalance``: model-predictive time sharing. At every decision it solves the time-sharing LP
  (`autopower.planner.timesharing`) from the *remaining* energies, orders the LP's phases to start
  with the current configuration and to migrate least, and follows the first phase until the
  LP says to switch (``revisit_at_s``). A switch happens only when the schedule's predicted
  lifetime, migrations paid, beats staying by ``min_gain`` (hysteresis: no flapping); phases
  shorter than ``min_phase_s`` are dropped. This is how a policy gets within a hair of the bound.
- ``subgroup``: the peer-to-peer rule of issue 5. The robots that can still reach each other
  (a connected part of the network, the base station included only if it is part of it)
  reallocate among themselves with `subgroup_reallocation`, without changing media; periodically
  re-run so that uneven drain is rebalanced locally.

Migration costs (`MigrationCosts`, from the scenario's ``[migration]`` table) are charged per
moved stage: its state crosses the radios on the route from the old to the new host (every hop's
sender pays send power, the receiver receive power, for the airtime), both hosts spend ``cpu_s``
busy CPU seconds, and the stage misses ``ceil((downtime_s + airtime) / period)`` runs.

Chains whose sink cannot be reached (the operator is cut off) degrade instead of stopping: their
results are buffered at the source robot (the chain's sink becomes its source), and decisions say so.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass, field
from typing import Mapping, Protocol, Sequence

import networkx as nx
import numpy as np

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.energy import LoadSpace, Network, airtime_s, build_network, load_of, media_choices
from autopower.model.mission_events import MissionEvent
from autopower.model.scenario import Chain, Scenario
from autopower.planner.exhaustive import TIE_REL
from autopower.planner.lp import INF, LinearProgram
from autopower.planner.problem import PlanRequest, make_problem

EXHAUSTIVE_UP_TO = 20_000  # combinations (all media) enumerated exactly; beyond, the MILP decides
NEVER = math.inf

__all__ = [
    "Decision", "MigrationCosts", "Move", "Policy", "POLICY_NAMES", "RebalancePolicy", "ReactivePolicy",
    "SchedulePhase", "StaticPolicy", "SubgroupPolicy", "SubgroupProposal", "TeamState", "candidate_networks",
    "base_media", "derive_network", "effective_scenario", "make_policy", "plan_moves", "subgroup_reallocation",
    "subgroups", "total_energy",
]


# ---------------------------------------------------------------------------------------------
# Values exchanged with the caller
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class MigrationCosts:
    """What moving one stage costs. Defaults fit the real components (MCL state ~32.5 kB)."""

    downtime_s: float = 0.5  # the stage does not run for this long (plus the state's airtime)
    cpu_s: float = 0.05  # busy CPU seconds to export (old host) and to import (new host) the state
    state_bytes_default: int = 32_768
    state_bytes: Mapping[str, int] = field(default_factory=dict)  # component type -> bytes

    @classmethod
    def from_scenario(cls, scenario: Scenario, overrides: Mapping | None = None) -> "MigrationCosts":
        """The scenario's ``[migration]`` table, then `overrides` (an events file's), then defaults."""
        values: dict = {**dict(scenario.migration), **dict(overrides or {})}
        out = cls()
        kwargs = {}
        for key in ("downtime_s", "cpu_s"):
            if key in values:
                kwargs[key] = float(values[key])
        if "state_bytes_default" in values:
            kwargs["state_bytes_default"] = int(values["state_bytes_default"])
        if "state_bytes" in values:
            kwargs["state_bytes"] = {k: int(v) for k, v in dict(values["state_bytes"]).items()}
        return dataclasses.replace(out, **kwargs)

    def state_bytes_for(self, component: str) -> int:
        return int(self.state_bytes.get(component, self.state_bytes_default))


@dataclass(frozen=True, kw_only=True)
class Move:
    """One stage changing host, with what it costs."""

    stage: str
    chain: str
    from_node: str
    to_node: str
    state_bytes: int
    transfer_s: float  # airtime of the state along the route (0 when the state is lost)
    downtime_s: float
    missed_periods: int
    energy_j: Mapping[str, float]  # robot -> joules charged for this move
    state_lost: bool  # the old host was gone or unreachable: the stage restarts cold

    def describe(self) -> str:
        how = "cold start (state lost)" if self.state_lost else f"{self.state_bytes} B in {self.transfer_s:.3f} s"
        joules = sum(self.energy_j.values())
        return (f"{self.stage}: {self.from_node} → {self.to_node}, {how}, {joules:.3f} J, "
                f"{self.missed_periods} missed period(s)")

    def to_dict(self) -> dict:
        return {"stage": self.stage, "chain": self.chain, "from": self.from_node, "to": self.to_node,
                "state_bytes": self.state_bytes, "transfer_s": self.transfer_s, "downtime_s": self.downtime_s,
                "missed_periods": self.missed_periods, "energy_j": dict(self.energy_j),
                "state_lost": self.state_lost}


@dataclass(frozen=True, kw_only=True)
class SchedulePhase:
    """A configuration to run for a while (the rebalance policy's plan ahead)."""

    network: Network
    allocation: Mapping[str, str]
    duration_s: float


@dataclass(frozen=True, kw_only=True)
class TeamState:
    """Everything a policy may know. Build it from the simulator's state or the base station's."""

    scenario: Scenario
    time_s: float  # mission (virtual) seconds
    network: Network  # the links the team uses now: media chosen, faults and cuts applied
    allocation: Mapping[str, str]  # stage -> host now; empty before the first decision
    energies_j: Mapping[str, float]  # remaining battery of the robots present (as measured)
    disabled_chains: frozenset[str] = frozenset()
    unavailable_nodes: frozenset[str] = frozenset()  # robots that left, died or cannot be reached
    topology: str | None = None  # whose media may be re-chosen (default: the scenario's)
    cut_links: frozenset[frozenset[str]] = frozenset()
    radio_faults: Mapping[str, tuple[str | None, str | None]] = field(default_factory=dict)
    # robot -> (medium of its links to the base station, medium of its links to robots); None = unchanged
    media_locked: bool = False  # keep `network`'s media (e.g. an operator override)
    accounting: str | None = None  # default: the scenario's
    events: tuple[MissionEvent, ...] = ()  # what happened since the last decision (for the reasons)
    migration: MigrationCosts = MigrationCosts()
    schedule: tuple[SchedulePhase, ...] = ()  # the phases the last decision planned after its own


@dataclass(frozen=True, kw_only=True)
class Decision:
    """A new configuration and why. Apply `moves` (migrations), start `started`, stop `stopped`."""

    policy: str
    time_s: float
    network: Network
    allocation: Mapping[str, str]  # every stage that runs from now on -> its host
    moves: tuple[Move, ...] = ()
    started: tuple[str, ...] = ()  # stages that start fresh (first plan, enabled chain, robot joined)
    stopped: tuple[str, ...] = ()  # stages that stop (chain disabled, robot gone)
    reasons: tuple[str, ...] = ()
    stage_reasons: Mapping[str, str] = field(default_factory=dict)  # the planner's why, per placed stage
    predicted_lifetime_s: float = 0.0  # remaining, from time_s, if nothing else happens
    predicted_gain_s: float = 0.0  # over keeping the current configuration (inf if it could not go on)
    migration_energy_j: Mapping[str, float] = field(default_factory=dict)
    forced: bool = False  # the current configuration could not continue
    schedule: tuple[SchedulePhase, ...] = ()  # phases planned after this one (carry into the next TeamState)
    revisit_at_s: float | None = None  # ask again at this mission time even without events
    dropped: Mapping[str, str] = field(default_factory=dict)  # chains that cannot run, and why
    degraded: Mapping[str, str] = field(default_factory=dict)  # chains whose results are buffered, and why

    @property
    def changes_anything(self) -> bool:
        return bool(self.moves or self.started or self.stopped)

    def to_dict(self) -> dict:
        return {
            "policy": self.policy, "time_s": self.time_s, "allocation": dict(self.allocation),
            "media": self.network.media_by_group(), "moves": [m.to_dict() for m in self.moves],
            "started": list(self.started), "stopped": list(self.stopped), "reasons": list(self.reasons),
            "predicted_lifetime_s": _finite(self.predicted_lifetime_s),
            "predicted_gain_s": _finite(self.predicted_gain_s),
            "migration_energy_j": dict(self.migration_energy_j), "forced": self.forced,
            "schedule": [{"duration_s": p.duration_s, "allocation": dict(p.allocation),
                          "media": p.network.media_by_group()} for p in self.schedule],
            "revisit_at_s": self.revisit_at_s, "dropped": dict(self.dropped), "degraded": dict(self.degraded),
        }


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


class Policy(Protocol):
    name: str

    def decide(self, state: TeamState) -> Decision | None:
        """A new configuration, or None to keep the current one (and no timer)."""
        ...


# ---------------------------------------------------------------------------------------------
# The world as the policy sees it: networks, degraded chains, migrations
# ---------------------------------------------------------------------------------------------


def derive_network(scenario: Scenario, topology: str | None, media: Mapping[str, str],
                   cut_links: frozenset[frozenset[str]] = frozenset(),
                   radio_faults: Mapping[str, tuple[str | None, str | None]] | None = None,
                   unavailable: frozenset[str] = frozenset()) -> Network:
    """The network of a topology and media choice after cuts, radio faults and departures."""
    network = build_network(scenario, topology, {g: m for g, m in media.items()
                                                 if g in {s.group for s in scenario.link_specs(topology)}})
    for pair in sorted(tuple(sorted(p)) for p in cut_links):
        network = network.without_link(*pair)
    for robot, (laptop_robot, robot_robot) in sorted((radio_faults or {}).items()):
        network = network.with_node_media(robot, laptop_robot=laptop_robot, robot_robot=robot_robot)
    if unavailable:
        network = network.without_nodes(set(unavailable))
    return network


def base_media(network: Network) -> dict[str, str]:
    """The media choice (group -> medium) a network was built from; faulted links excluded."""
    return {g: m for g, m in network.media_by_group().items() if "@" not in g}


def candidate_networks(state: TeamState) -> list[Network]:
    """Every network the team could switch to now: one per media choice the faults leave open."""
    gone = frozenset(state.unavailable_nodes)
    if state.media_locked:
        return [state.network.without_nodes(set(gone)) if gone & set(state.network.nodes) else state.network]
    out: list[Network] = []
    for media in media_choices(state.scenario, state.topology):
        net = derive_network(state.scenario, state.topology, media, state.cut_links, state.radio_faults, gone)
        if net not in out:
            out.append(net)
    return out


def effective_scenario(scenario: Scenario, network: Network) -> tuple[Scenario, dict[str, str]]:
    """The scenario with every chain whose sink is unreachable made to buffer at its source."""
    degraded: dict[str, str] = {}
    chains = []
    for chain in scenario.chains:
        if (chain.source in network.nodes and chain.sink != chain.source
                and not network.reachable(chain.source, chain.sink)):
            degraded[chain.name] = (f"{chain.name}: {chain.sink} is unreachable from {chain.source}; "
                                    f"results are buffered at {chain.source} until it returns")
            chain = dataclasses.replace(chain, sink=chain.source)
        chains.append(chain)
    if not degraded:
        return scenario, degraded
    return dataclasses.replace(scenario, chains=tuple(chains)), degraded


def _move(scenario: Scenario, network: Network, chain: Chain, stage: str, component: str, old: str, new: str,
          costs: MigrationCosts) -> Move:
    energy: dict[str, float] = {}
    base = network.basestation

    def charge(node: str, joules: float) -> None:
        if node != base and node in network.nodes and joules:
            energy[node] = energy.get(node, 0.0) + joules

    size = costs.state_bytes_for(component)
    lost = old not in network.nodes or not network.reachable(old, new)
    transfer = 0.0
    if not lost:
        for u, v, medium in network.route(old, new):
            radio = scenario.radios[medium]
            air = airtime_s(size, radio)
            transfer += air
            charge(u, radio.send_w * air)
            charge(v, radio.receive_w * air)
        charge(old, _busy_extra_w(scenario, old) * costs.cpu_s)
    charge(new, _busy_extra_w(scenario, new) * costs.cpu_s)
    down = costs.downtime_s + transfer
    return Move(stage=stage, chain=chain.name, from_node=old, to_node=new, state_bytes=0 if lost else size,
                transfer_s=transfer, downtime_s=down, missed_periods=math.ceil(down / chain.period_s - 1e-9),
                energy_j=energy, state_lost=lost)


def _busy_extra_w(scenario: Scenario, node: str) -> float:
    platform = scenario.platform_of(node)
    return 0.0 if platform.mains else platform.busy_w - platform.idle_w


def plan_moves(scenario: Scenario, network: Network, old: Mapping[str, str], new: Mapping[str, str],
               costs: MigrationCosts) -> list[Move]:
    """The migrations that turn allocation `old` into `new` on `network` (stages in both only)."""
    out = []
    for chain in scenario.chains:
        for stage in chain.stages:
            a, b = old.get(stage.name), new.get(stage.name)
            if a is not None and b is not None and a != b:
                out.append(_move(scenario, network, chain, stage.name, stage.component, a, b, costs))
    return out


def beats(value_s: float, than_s: float, min_gain: float, min_gain_s: float) -> bool:
    """The hysteresis every policy applies: ``value_s`` must exceed ``than_s`` by a fraction and a margin."""
    return value_s > than_s * (1 + min_gain) + min_gain_s


def total_energy(moves: Sequence[Move]) -> dict[str, float]:
    out: dict[str, float] = {}
    for m in moves:
        for robot, joules in m.energy_j.items():
            out[robot] = out.get(robot, 0.0) + joules
    return out


# ---------------------------------------------------------------------------------------------
# One decision's view: the problem, energies, configurations and their values
# ---------------------------------------------------------------------------------------------


@dataclass
class _Option:
    network: Network
    allocation: dict[str, str]
    value_s: float  # predicted remaining lifetime, migrations paid
    moves: list[Move]
    spread: float = 0.0  # sum_i P_i / E_i: the planner's tie-breaker
    label: str = ""
    schedule: list[SchedulePhase] = field(default_factory=list)  # for schedule options: all phases


class _View:
    def __init__(self, state: TeamState):
        self.state = state
        self.networks = candidate_networks(state)
        if not self.networks:
            raise InfeasibleError("no network is left to run on")
        self.gone = frozenset(state.unavailable_nodes)
        raw = state.scenario
        self.scenario, self.degraded = effective_scenario(raw, self.networks[0])
        self.accounting = state.accounting or raw.accounting
        self.base = self.networks[0].basestation
        self.robots = [n for n in self.networks[0].nodes if n != self.base]
        energies = {r: float(state.energies_j.get(r, raw.robot(r).energy_j)) for r in self.robots}
        self.energies = {r: max(e, 1e-9) for r, e in energies.items()}
        self.energy = np.array([self.energies[r] for r in self.robots])
        request = PlanRequest(scenario=self.scenario, network=self.networks[0], energies_j=self.energies,
                              disabled_chains=frozenset(state.disabled_chains), unavailable_nodes=self.gone,
                              accounting=self.accounting)
        self.problem = make_problem(request)
        self.problem.networks = list(self.networks)
        self.stages = [s.name for c in self.problem.chains for s in c.stages]
        self.current = {s: h for s, h in state.allocation.items() if s in self.stages}
        self._spaces: dict[Network, LoadSpace] = {}

    # ---- evaluation ------------------------------------------------------------------------------
    def space(self, network: Network) -> LoadSpace:
        space = self._spaces.get(network)
        if space is None:
            space = self._spaces[network] = LoadSpace(self.scenario, network, self.accounting, self.energies)
        return space

    def power(self, network: Network, allocation: Mapping[str, str]) -> tuple[np.ndarray, bool]:
        space = self.space(network)
        load = load_of(space, self.problem.chains, allocation)[None, :]
        return space.total_power(load)[0], bool(space.feasible(load)[0])

    def stay_network(self) -> Network:
        """The network in use now, minus nodes that are gone and links known to be cut."""
        net = self.state.network
        extra = set(net.nodes) - set(self.networks[0].nodes)
        if extra:
            net = net.without_nodes(extra)
        for pair in sorted(tuple(sorted(p)) for p in self.state.cut_links):
            if net.medium_between(*pair) is not None:
                net = net.without_link(*pair)
        return net

    def stay_valid(self) -> bool:
        """Can the current configuration go on as it is (every stage placed, routable, feasible)?"""
        if set(self.current) != set(self.stages):
            return False
        net = self.stay_network()
        for chain in self.problem.chains:
            for stage in chain.stages:
                host = self.current[stage.name]
                if host not in net.nodes or not (net.reachable(chain.source, host) and net.reachable(host, chain.sink)):
                    return False
                if stage.pin is not None and host != stage.pin:
                    return False
        return self.power(net, self.current)[1]

    def stay_problems(self) -> list[str]:
        """Why the current configuration cannot go on, in words."""
        out = []
        net = self.stay_network()
        for chain in self.problem.chains:
            for stage in chain.stages:
                host = self.current.get(stage.name)
                if host is None:
                    out.append(f"{stage.name} is not running")
                elif host not in net.nodes:
                    out.append(f"{stage.name}'s host {host} is gone")
                elif not (net.reachable(chain.source, host) and net.reachable(host, chain.sink)):
                    out.append(f"{stage.name} on {host} is cut off from {chain.source}"
                               + (f" or {chain.sink}" if chain.sink != chain.source else ""))
        if not out:
            from autopower.model.energy import evaluate

            try:
                ev = evaluate(self.scenario, net, self.current, accounting=self.accounting, energies_j=self.energies,
                              disabled_chains=frozenset(c.name for c in self.scenario.chains)
                              - {c.name for c in self.problem.chains})
                out.extend(v.message for v in ev.violations)
            except AutoPowerError as exc:
                out.append(str(exc))
        return out

    def value(self, network: Network, allocation: Mapping[str, str], label: str = "") -> _Option:
        moves = plan_moves(self.scenario, network, self.current, allocation, self.state.migration)
        power, feasible = self.power(network, allocation)
        cost = total_energy(moves)
        energy = self.energy - np.array([cost.get(r, 0.0) for r in self.robots])
        life = float(np.min(np.maximum(energy, 0.0) / power)) if feasible and len(power) else -NEVER
        if feasible and not len(power):
            life = NEVER
        return _Option(network, dict(allocation), life, moves, float((power / self.energy).sum()), label)

    def stay(self) -> _Option | None:
        if not self.stay_valid():
            return None
        return self.value(self.stay_network(), self.current, "stay")

    # ---- search --------------------------------------------------------------------------------
    def best_static(self, hosts: Mapping[str, Sequence[str]] | None = None) -> _Option | None:
        """The configuration with the longest predicted life, migrations paid (ties: fewest moves)."""
        if not self.problem.chains:
            return self.value(self.stay_network() if self.stay_network() in self.networks else self.networks[0],
                              {}, "optimum")
        if self.problem.combinations() <= EXHAUSTIVE_UP_TO:
            return self._enumerate(hosts)
        from autopower.planner.milp import solve_milp

        result = solve_milp(self.problem, time_limit_s=30.0, mip_rel_gap=1e-6)
        if result.allocation is None:
            return None
        # the MILP ignores migration costs; callers weigh its plan against staying, costs included
        return self.value(result.network, result.allocation, "optimum")

    def _enumerate(self, hosts: Mapping[str, Sequence[str]] | None = None) -> _Option | None:
        best: tuple | None = None
        for network in self.networks:
            found = _enumerate_network(self, network, self.problem.chains, hosts or self.problem.hosts, self.current)
            if found is None:
                continue
            key = (found[0], -found[1], -found[2])
            if best is None or _better(found[0], best[0][0], key, best[0]):
                best = (key, network, found[3])
        if best is None:
            return None
        return self.value(best[1], best[2], "optimum")

    def explain(self, network: Network, allocation: Mapping[str, str], stages: Sequence[str]) -> dict[str, str]:
        if not stages:
            return {}
        try:
            from autopower.planner import evaluate_in
            from autopower.planner.reasons import explain

            problem = dataclasses.replace(self.problem, networks=[network])
            why = explain(problem, network, dict(allocation), evaluate_in(problem, network, dict(allocation)))
            return {s: why[s] for s in stages if s in why}
        except AutoPowerError:  # pragma: no cover - explanations are a courtesy
            return {}


def _better(value: float, best_value: float, key: tuple, best_key: tuple) -> bool:
    if value > best_value * (1 + TIE_REL) + 1e-12:
        return True
    if value < best_value * (1 - TIE_REL) - 1e-12:
        return False
    return key[1:] > best_key[1:]


def _enumerate_network(view: _View, network: Network, chains: Sequence[Chain], hosts: Mapping[str, Sequence[str]],
                       current: Mapping[str, str], base_load: np.ndarray | None = None,
                       lifetime_of: Sequence[str] | None = None):
    """Exhaustive search on one network, migrations included: (value, moves, -spread, allocation)."""
    space = view.space(network)
    robots = space.robots
    index = {r: i for i, r in enumerate(robots)}
    loads = np.zeros((1, space.size)) if base_load is None else base_load[None, :].copy()
    costs = np.zeros((1, len(robots)))
    moves = np.zeros(1)
    options = []
    for chain in chains:
        opts = list(itertools.product(*(hosts[s.name] for s in chain.stages)))
        rows = np.array([space.chain_load(chain, o) for o in opts])
        crow = np.zeros((len(opts), len(robots)))
        mrow = np.zeros(len(opts))
        for k, opt in enumerate(opts):
            for stage, host in zip(chain.stages, opt):
                old = current.get(stage.name)
                if old is not None and old != host:
                    mv = _move(view.scenario, network, chain, stage.name, stage.component, old, host,
                               view.state.migration)
                    mrow[k] += 1
                    for robot, joules in mv.energy_j.items():
                        if robot in index:
                            crow[k, index[robot]] += joules
        loads = (loads[:, None, :] + rows[None, :, :]).reshape(-1, space.size)
        costs = (costs[:, None, :] + crow[None, :, :]).reshape(-1, len(robots))
        moves = (moves[:, None] + mrow[None, :]).reshape(-1)
        options.append(opts)
    power = space.total_power(loads)
    energy = np.maximum(space.energy_j[None, :] - costs, 0.0)
    cols = list(range(len(robots))) if lifetime_of is None else [index[r] for r in lifetime_of if r in index]
    life = (energy / power)[:, cols].min(axis=1) if cols else np.full(len(loads), NEVER)
    life = np.where(space.feasible(loads), life, -np.inf)
    best = life.max()
    if not np.isfinite(best) and best < 0:
        return None
    ties = np.flatnonzero(life >= best * (1 - TIE_REL) - 1e-12)
    spread = (power / space.energy_j).sum(axis=1)
    k = int(min(ties, key=lambda j: (moves[j], spread[j], j)))
    sizes = [len(o) for o in options]
    picks = np.unravel_index(k, sizes) if sizes else ()
    allocation = {}
    for chain, opts, pick in zip(chains, options, picks):
        for stage, host in zip(chain.stages, opts[int(pick)]):
            allocation[stage.name] = host
    return float(life[k]), float(moves[k]), float(spread[k]), allocation


# ---------------------------------------------------------------------------------------------
# Building decisions
# ---------------------------------------------------------------------------------------------


def _decision(policy: str, view: _View, option: _Option, *, reasons: list[str], forced: bool,
              stay_value: float | None, schedule: Sequence[SchedulePhase] = (), revisit_at_s: float | None = None,
              predicted_s: float | None = None) -> Decision:
    state = view.state
    old = dict(state.allocation)
    new = option.allocation
    moves = tuple(plan_moves(view.scenario, option.network, view.current, new, state.migration))
    started = tuple(s for s in new if s not in view.current)
    stopped = tuple(s for s in old if s not in new)
    predicted = option.value_s if predicted_s is None else predicted_s
    gain = NEVER if stay_value is None else predicted - stay_value
    for name, why in view.degraded.items():
        if any(c.name == name for c in view.problem.chains):
            reasons.append(why)
    for name, why in view.problem.unroutable.items():
        reasons.append(f"not running: {why}")
    return Decision(
        policy=policy, time_s=state.time_s, network=option.network, allocation=dict(new), moves=moves,
        started=started, stopped=stopped, reasons=tuple(dict.fromkeys(r for r in reasons if r)),
        stage_reasons=view.explain(option.network, new, [m.stage for m in moves] + list(started)),
        predicted_lifetime_s=predicted, predicted_gain_s=gain, migration_energy_j=total_energy(moves),
        forced=forced, schedule=tuple(schedule), revisit_at_s=revisit_at_s,
        dropped=dict(view.problem.unroutable),
        degraded={k: v for k, v in view.degraded.items() if any(c.name == k for c in view.problem.chains)},
    )


def _what_happened(state: TeamState) -> str:
    return "; ".join(e.describe() for e in state.events) if state.events else ""


def _forced_reason(view: _View) -> str:
    happened = _what_happened(view.state)
    if not view.state.allocation:
        return "mission start"
    problems = view.stay_problems()
    return ("the current configuration cannot continue" + (f" after {happened}" if happened else "")
            + (f": {'; '.join(problems)}" if problems else ""))


def _no_placement(view: _View) -> InfeasibleError:
    local = {s.name: c.source for c in view.problem.chains for s in c.stages}
    why = ""
    try:
        space = view.space(view.networks[0])
        load = load_of(space, view.problem.chains, local)[None, :]
        if not space.feasible(load)[0]:
            why = " (even running every stage locally exceeds a CPU or radio limit)"
    except AutoPowerError:
        pass
    return InfeasibleError(f"at {view.state.time_s:.1f} s no allocation meets the CPU and radio limits{why}"
                           + (f" after: {_what_happened(view.state)}" if view.state.events else ""))


class StaticPolicy:
    """The best fixed plan; on a forced change: local repair, then all-local, then the optimum."""

    name = "static"

    def decide(self, state: TeamState) -> Decision | None:
        view = _View(state)
        if not state.allocation:
            best = view.best_static()
            if best is None:
                raise _no_placement(view)
            return _decision(self.name, view, best, reasons=["mission start: the best static plan"],
                             forced=True, stay_value=None)
        if view.stay_valid():
            stopped = [s for s in state.allocation if s not in view.stages]
            if not stopped:
                return None
            option = view.value(view.stay_network(), view.current, "stay")
            return _decision(self.name, view, option, reasons=[f"stopping {', '.join(stopped)}: "
                                                               + (_what_happened(state) or "chain no longer runs")],
                             forced=False, stay_value=option.value_s)
        network = view.stay_network()
        if network not in view.networks:
            network = view.networks[0]
        repair = dict(view.current)
        for chain in view.problem.chains:
            for stage in chain.stages:
                host = repair.get(stage.name)
                if host is None or host not in view.problem.hosts[stage.name]:
                    allowed = view.problem.hosts[stage.name]
                    repair[stage.name] = chain.source if chain.source in allowed else allowed[0]
        reason = _forced_reason(view)
        option = view.value(network, repair, "repair")
        if option.value_s > -NEVER:
            return _decision(self.name, view, option, forced=True, stay_value=None,
                             reasons=[reason, "static: stages that lost their host run locally"])
        local = {s.name: (c.source if c.source in view.problem.hosts[s.name] else view.problem.hosts[s.name][0])
                 for c in view.problem.chains for s in c.stages}
        option = view.value(network, local, "all-local")
        if option.value_s > -NEVER:
            return _decision(self.name, view, option, forced=True, stay_value=None,
                             reasons=[reason, "static: reverting to the all-local configuration (the paper's "
                                              "baseline), since keeping the plan is infeasible"])
        best = view.best_static()
        if best is None:
            raise _no_placement(view)
        return _decision(self.name, view, best, forced=True, stay_value=None,
                         reasons=[reason, "static: even all-local is infeasible; switching to the optimum"])


class ReactivePolicy:
    """Replan on events only; move only if the new plan outlives the old one after migrations."""

    name = "reactive"

    def __init__(self, min_gain: float = 0.001, min_gain_s: float = 10.0):
        self.min_gain = min_gain
        self.min_gain_s = min_gain_s

    def decide(self, state: TeamState) -> Decision | None:
        view = _View(state)
        stay = view.stay()
        if stay is not None and not state.events:
            return None
        best = view.best_static()
        if best is None:
            if stay is None:
                raise _no_placement(view)
            return None
        if stay is None:
            return _decision(self.name, view, best, forced=True, stay_value=None,
                             reasons=[_forced_reason(view), "replanned from the remaining energies"])
        stopped = [s for s in state.allocation if s not in view.stages]
        if beats(best.value_s, stay.value_s, self.min_gain, self.min_gain_s):
            return _decision(self.name, view, best, forced=False, stay_value=stay.value_s,
                             reasons=[f"after {_what_happened(state)}: replanned; predicted lifetime "
                                      f"{stay.value_s:,.0f} s → {best.value_s:,.0f} s "
                                      f"({best.value_s / stay.value_s - 1:+.2%}) after migrations"])
        keep = (f"after {_what_happened(state)}: " + (f"stopping {', '.join(stopped)}; " if stopped else "")
                + f"keeping the plan (the best alternative predicts {best.value_s:,.0f} s vs {stay.value_s:,.0f} s; "
                f"a move must gain {self.min_gain:.1%} + {self.min_gain_s:g} s)")
        return _decision(self.name, view, stay, forced=False, stay_value=stay.value_s, reasons=[keep])


class RebalancePolicy:
    """Model-predictive time sharing with hysteresis (see the module docstring)."""

    name = "rebalance"

    def __init__(self, min_gain: float = 0.001, min_gain_s: float = 10.0, min_phase_s: float = 60.0,
                 min_phase_fraction: float = 0.01):
        self.min_gain = min_gain
        self.min_gain_s = min_gain_s
        self.min_phase_s = min_phase_s
        self.min_phase_fraction = min_phase_fraction

    def decide(self, state: TeamState) -> Decision | None:
        view = _View(state)
        stay = view.stay()
        best = view.best_static()
        if best is None and stay is None:
            raise _no_placement(view)
        sched = self._schedule_option(view, best, stay)
        if sched is not None and best is not None and not beats(sched.value_s, best.value_s, self.min_gain,
                                                                   self.min_gain_s):
            # a schedule that barely beats the best fixed configuration is not worth its switches:
            # its predicted few seconds are within what a switch can cost beyond the model
            sched = None
        options = [o for o in (best, sched) if o is not None]
        choice = max(options, key=lambda o: o.value_s) if options else stay
        if stay is None:
            return self._emit(view, choice, stay, forced=True, why=_forced_reason(view))
        stopped = [s for s in state.allocation if s not in view.stages]
        same = _same_config(view, choice, stay)
        if same and choice.schedule:
            # the schedule starts with what runs now: nothing moves, come back when its phase ends
            return self._emit(view, choice, stay, forced=False,
                              why=f"stopping {', '.join(stopped)}" if stopped else "", quiet=not stopped)
        if beats(choice.value_s, stay.value_s, self.min_gain, self.min_gain_s) and not same:
            what = _what_happened(state)
            return self._emit(view, choice, stay, forced=False,
                              why=(f"after {what}: " if what else "") + "rebalancing")
        # Staying is (within the hysteresis) as good as any schedule from here: following it to the
        # end keeps it so, since the LP from later energies on this path has the same optimum.
        if stopped:
            return _decision(self.name, view, stay, forced=False, stay_value=stay.value_s,
                             reasons=[f"stopping {', '.join(stopped)}"])
        return None

    # ---- the time-sharing schedule from the remaining energies ----------------------------------
    def _schedule_option(self, view: _View, best: _Option | None, stay: _Option | None) -> _Option | None:
        from autopower.planner.timesharing import time_sharing_bound

        if not view.problem.chains:
            return None
        seeds = [(o.network, o.allocation) for o in (best, stay) if o is not None]
        try:
            bound = time_sharing_bound(view.problem, seeds)
        except AutoPowerError:  # pragma: no cover - the bound is an optimisation, not a necessity
            return None
        lifetime = bound.achieved_s
        schedule = [(p.network, dict(p.allocation), p.duration_s) for p in bound.schedule]
        phases = [(n, a) for n, a, _ in schedule]
        if len(phases) <= 1:
            return None
        shortest = max(self.min_phase_s, self.min_phase_fraction * lifetime)
        durations = [d for _, _, d in schedule]
        while len(phases) > 1 and min(durations) < shortest:
            keep = [k for k, d in enumerate(durations) if d >= shortest] or [int(np.argmax(durations))]
            phases = [phases[k] for k in keep]
            durations = _restricted_lp(view, phases)
            keep = [k for k, d in enumerate(durations) if d > 1e-6]
            phases, durations = [phases[k] for k in keep], [durations[k] for k in keep]
        if len(phases) <= 1:
            return None
        order = _order_phases(view, phases, durations)
        return _schedule_value(view, [phases[k] for k in order], [durations[k] for k in order])

    def _emit(self, view: _View, choice: _Option, stay: _Option | None, *, forced: bool, why: str,
              quiet: bool = False) -> Decision:
        state = view.state
        reasons = [] if quiet else [why]
        stay_value = None if stay is None else stay.value_s
        if choice.schedule:
            first, rest = choice.schedule[0], choice.schedule[1:]
            lines = ", ".join(f"{p.duration_s:,.0f} s" for p in choice.schedule)
            if not quiet:
                reasons.append(f"time sharing over {len(choice.schedule)} configurations ({lines}): predicted "
                               f"{choice.value_s:,.0f} s" + ("" if stay is None else
                                                             f" vs {stay.value_s:,.0f} s staying"))
            return _decision(self.name, view, dataclasses.replace(choice, network=first.network,
                                                                  allocation=dict(first.allocation)),
                             reasons=reasons, forced=forced, stay_value=stay_value, schedule=rest,
                             revisit_at_s=state.time_s + first.duration_s, predicted_s=choice.value_s)
        if not quiet:
            reasons.append(f"the best single configuration: predicted {choice.value_s:,.0f} s"
                           + ("" if stay is None else f" vs {stay.value_s:,.0f} s staying"))
        return _decision(self.name, view, choice, reasons=reasons, forced=forced, stay_value=stay_value)


def _same_config(view: _View, option: _Option, stay: _Option) -> bool:
    first_net = option.schedule[0].network if option.schedule else option.network
    first_alloc = option.schedule[0].allocation if option.schedule else option.allocation
    return first_net == stay.network and dict(first_alloc) == dict(stay.allocation)




def _restricted_lp(view: _View, phases: list[tuple[Network, dict[str, str]]]) -> list[float]:
    """Durations maximising the total over these configurations only (the time-sharing LP)."""
    powers = [view.power(n, a)[0] for n, a in phases]
    lp = LinearProgram()
    cols = [lp.var(0.0, INF, cost=-1.0) for _ in phases]
    for i in range(len(view.robots)):
        lp.row({c: float(p[i]) for c, p in zip(cols, powers)}, -INF, float(view.energy[i]))
    sol = lp.solve()
    if not sol.has_solution:  # pragma: no cover - the LP is always feasible (t = 0)
        return [0.0] * len(phases)
    return [float(v) for v in sol.values]


def _order_phases(view: _View, phases: list[tuple[Network, dict[str, str]]], durations: list[float]) -> list[int]:
    """Start with what runs now (or what the last decision planned next), then migrate least."""
    current = (view.stay_network(), view.current)
    committed = [(p.network, dict(p.allocation)) for p in view.state.schedule]

    def cost(a: tuple[Network, Mapping[str, str]], b: tuple[Network, Mapping[str, str]]) -> tuple[float, int]:
        moves = plan_moves(view.scenario, b[0], a[1], b[1], view.state.migration)
        return sum(total_energy(moves).values()), len(moves) + (a[0] != b[0])

    left = list(range(len(phases)))
    order: list[int] = []
    for k in left:
        if phases[k][0] == current[0] and phases[k][1] == current[1]:
            order.append(k)
            break
    if not order:
        for planned in committed:
            match = [k for k in left if phases[k][0] == planned[0] and phases[k][1] == planned[1]]
            if match:
                order.append(match[0])
                break
    prev = current if not order else phases[order[0]]
    left = [k for k in left if k not in order]
    while left:
        k = min(left, key=lambda j: (cost(prev, phases[j]), -durations[j], j))
        order.append(k)
        left.remove(k)
        prev = phases[k]
    return order


def _schedule_value(view: _View, phases: list[tuple[Network, dict[str, str]]], durations: list[float]) -> _Option:
    """Predicted remaining life following these phases in order, migrations paid."""
    energy = view.energy.copy()
    prev = view.current
    total = 0.0
    out: list[SchedulePhase] = []
    first_moves: list[Move] = []
    for k, ((network, allocation), duration) in enumerate(zip(phases, durations)):
        moves = plan_moves(view.scenario, network, prev, allocation, view.state.migration)
        if k == 0:
            first_moves = moves
        cost = total_energy(moves)
        energy = energy - np.array([cost.get(r, 0.0) for r in view.robots])
        power, feasible = view.power(network, allocation)
        if not feasible or (energy <= 0).any():
            total = -NEVER if k == 0 else total
            break
        room = float(np.min(energy / power)) if len(power) else NEVER
        last = k == len(phases) - 1
        run = room if last else min(duration, room)
        out.append(SchedulePhase(network=network, allocation=dict(allocation), duration_s=run))
        total += run
        energy = energy - power * (run if math.isfinite(run) else 0.0)
        prev = allocation
        if run < duration and not last:
            break
    first = out[0] if out else SchedulePhase(network=phases[0][0], allocation=phases[0][1], duration_s=0.0)
    return _Option(first.network, dict(first.allocation), total, first_moves, 0.0, "schedule", out)


# ---------------------------------------------------------------------------------------------
# Subgroups: peer-to-peer reallocation among the robots that can still reach each other
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class SubgroupProposal:
    """What a subgroup agrees to do (issue 5's propose step). Empty `moves`: nothing worth doing."""

    members: tuple[str, ...]
    allocation: Mapping[str, str]  # the full allocation after the moves (stages outside untouched)
    moves: tuple[Move, ...]
    started: tuple[str, ...]  # stages of the subgroup that were not running at all
    min_lifetime_before_s: float | None  # the subgroup's shortest-lived member now; None if it cannot go on
    min_lifetime_after_s: float | None
    reasons: tuple[str, ...] = ()
    search: str = "exhaustive"  # "exhaustive" | "neighbourhood"

    @property
    def changes_anything(self) -> bool:
        return bool(self.moves or self.started)

    def to_dict(self) -> dict:
        return {"members": list(self.members), "allocation": dict(self.allocation),
                "moves": [m.to_dict() for m in self.moves], "started": list(self.started),
                "min_lifetime_before_s": self.min_lifetime_before_s, "min_lifetime_after_s": self.min_lifetime_after_s,
                "reasons": list(self.reasons), "search": self.search}


def subgroups(network: Network) -> list[tuple[str, ...]]:
    """The parts of the team that can reach each other (each with the base station if it is in it)."""
    out = []
    for part in sorted((set(c) for c in nx.connected_components(network.graph)),
                       key=lambda c: min(network.nodes.index(n) for n in c)):
        members = tuple(n for n in network.nodes if n in part)
        if any(n != network.basestation for n in members):
            out.append(members)
    return out


def subgroup_reallocation(scenario: Scenario, network: Network, members: Sequence[str],
                          allocation: Mapping[str, str], energies_j: Mapping[str, float], *,
                          accounting: str | None = None, disabled_chains: frozenset[str] = frozenset(),
                          migration: MigrationCosts | None = None, min_gain: float = 0.001,
                          min_gain_s: float = 10.0, max_enumeration: int = EXHAUSTIVE_UP_TO,
                          max_rounds: int = 50) -> SubgroupProposal:
    """A reallocation among `members` that raises their minimum lifetime, migrations paid.

    Only stages hosted by members (and stages of members' chains whose host is gone) move, only
    onto members; everything else is background load. Media stay as they are. Small cases are
    searched exhaustively; larger ones by a neighbourhood search that moves up to three chains'
    stages at once (multi-party moves: A→B, B→C, C→A), which escapes the local optima that
    pairwise swaps get stuck in. A proposal with no moves means no gain above `min_gain`.
    """
    members = tuple(dict.fromkeys(members))
    for m in members:
        if m not in network.nodes:
            raise AutoPowerError(f"subgroup member {m!r} is not on the network ({', '.join(network.nodes)})")
    state = TeamState(scenario=scenario, time_s=0.0, network=network, allocation=dict(allocation),
                      energies_j=dict(energies_j), disabled_chains=frozenset(disabled_chains), media_locked=True,
                      accounting=accounting, migration=migration or MigrationCosts.from_scenario(scenario))
    view = _View(state)
    member_set = set(members)
    robots = [m for m in members if m != network.basestation]
    net = view.networks[0]
    movable: list[Chain] = []
    fixed: list[Chain] = []
    hosts: dict[str, list[str]] = {}
    started = []
    broken = False  # some stage of the subgroup has no usable host now
    for chain in view.problem.chains:
        mine = False
        for stage in chain.stages:
            host = view.current.get(stage.name)
            stranded = host is None or host not in view.problem.hosts[stage.name]
            if (host in member_set) or (stranded and chain.source in member_set):
                allowed = [h for h in view.problem.hosts[stage.name] if h in member_set]
                hosts[stage.name] = allowed
                mine = True
                broken = broken or stranded
                if host is None:
                    started.append(stage.name)
            else:
                hosts[stage.name] = [host] if not stranded else []
        if mine and all(hosts[s.name] for s in chain.stages):
            movable.append(chain)
        elif all(view.current.get(s.name) in view.problem.hosts[s.name] for s in chain.stages):
            fixed.append(chain)
    space = view.space(net)
    base_load = np.zeros(space.size)
    for chain in fixed:
        base_load += space.chain_load(chain, tuple(view.current[s.name] for s in chain.stages))
    index = {r: i for i, r in enumerate(space.robots)}
    cols = [index[r] for r in robots if r in index]

    def life_of(alloc: Mapping[str, str]) -> float:
        load = base_load + sum((space.chain_load(c, tuple(alloc[s.name] for s in c.stages)) for c in movable),
                               np.zeros(space.size))
        if not space.feasible(load[None, :])[0]:
            return -NEVER
        moves = plan_moves(view.scenario, net, view.current, alloc, view.state.migration)
        cost = total_energy(moves)
        energy = np.maximum(space.energy_j - np.array([cost.get(r, 0.0) for r in space.robots]), 0.0)
        power = space.total_power(load[None, :])[0]
        return float((energy / power)[cols].min()) if cols else NEVER

    before = -NEVER if broken else life_of(view.current)
    combos = 1
    for chain in movable:
        for stage in chain.stages:
            combos *= len(hosts[stage.name])
    if combos <= max_enumeration:
        found = _enumerate_network(view, net, movable, hosts, view.current, base_load, robots)
        proposal = dict(view.current)
        if found is not None:
            proposal.update(found[3])
        search = "exhaustive"
    else:
        proposal = _neighbourhood_search(view, net, movable, hosts, base_load, robots, life_of, max_rounds)
        search = "neighbourhood"
    after = life_of(proposal)
    worth = after > -NEVER and (before == -NEVER or beats(after, before, min_gain, min_gain_s))
    final = dict(allocation)
    final.update(proposal if worth else {})
    moves = tuple(plan_moves(view.scenario, net, view.current, final, view.state.migration)) if worth else ()
    reasons = []
    if worth and (moves or started):
        b = "cannot go on" if before == -NEVER else f"{before:,.0f} s"
        reasons.append(f"subgroup {', '.join(members)}: shortest member life {b} → {after:,.0f} s"
                       f" with {len(moves)} move(s)" + (f" and {len(started)} restart(s)" if started else ""))
    elif not worth and before > -NEVER:
        reasons.append(f"subgroup {', '.join(members)}: no reallocation gains more than {min_gain:.1%} + {min_gain_s:g} s")
    else:
        reasons.append(f"subgroup {', '.join(members)}: no feasible reallocation among its members")
    for name, why in view.degraded.items():
        if any(c.name == name for c in movable):
            reasons.append(why)
    return SubgroupProposal(members=members, allocation=final, moves=moves,
                            started=tuple(started) if worth else (),
                            min_lifetime_before_s=None if before == -NEVER else before,
                            min_lifetime_after_s=None if after == -NEVER else after,
                            reasons=tuple(reasons), search=search)


def _neighbourhood_search(view: _View, network: Network, chains: list[Chain], hosts: Mapping[str, list[str]],
                          base_load: np.ndarray, robots: Sequence[str], life_of, max_rounds: int) -> dict[str, str]:
    """Re-place up to three chains at once (one of them on the bottleneck) until nothing gains.

    Each neighbourhood is searched exactly and vectorised, the other chains' loads held fixed.
    """
    space = view.space(network)
    current = dict(view.current)
    for chain in chains:  # stranded stages start on their source if allowed, else the first member
        for stage in chain.stages:
            if current.get(stage.name) not in hosts[stage.name]:
                allowed = hosts[stage.name]
                current[stage.name] = chain.source if chain.source in allowed else allowed[0]
    value = life_of(current)
    sizes = {c.name: math.prod(len(hosts[s.name]) for s in c.stages) for c in chains}
    index = {r: i for i, r in enumerate(space.robots)}
    for _ in range(max_rounds):
        loads = {c.name: space.chain_load(c, tuple(current[s.name] for s in c.stages)) for c in chains}
        total = base_load + sum(loads.values(), np.zeros(space.size))
        power = space.total_power(total[None, :])[0]
        worst = min((r for r in robots if r in index), key=lambda r: space.energy_j[index[r]] / power[index[r]],
                    default=None)
        hot = {c.name for c in chains if any(current[s.name] == worst for s in c.stages)} or {c.name for c in chains}
        best_value, best_alloc = value, None
        for size in (1, 2, 3):
            for group in itertools.combinations(chains, size):
                if not any(c.name in hot for c in group) or math.prod(sizes[c.name] for c in group) > 4096:
                    continue
                others = total - sum((loads[c.name] for c in group), np.zeros(space.size))
                found = _enumerate_network(view, network, group, hosts, view.current, others, robots)
                if found is None:
                    continue
                trial = {**current, **found[3]}
                if found[0] > best_value * (1 + 1e-9) + 1e-9 and trial != current:
                    v = life_of(trial)  # with every migration's cost, not only this group's
                    if v > best_value * (1 + 1e-9) + 1e-9:
                        best_value, best_alloc = v, trial
            if best_alloc is not None:
                break
        if best_alloc is None:
            break
        current, value = best_alloc, best_value
    return current


class SubgroupPolicy:
    """The peer-to-peer rule, applied to every connected part of the team (media unchanged)."""

    name = "subgroup"

    def __init__(self, min_gain: float = 0.001, min_gain_s: float = 10.0, recheck_fraction: float = 0.1,
                 min_recheck_s: float = 60.0):
        self.min_gain = min_gain
        self.min_gain_s = min_gain_s
        self.recheck_fraction = recheck_fraction
        self.min_recheck_s = min_recheck_s

    def decide(self, state: TeamState) -> Decision | None:
        view = _View(state)
        if not state.allocation:
            best = view.best_static()
            if best is None:
                raise _no_placement(view)
            return self._with_revisit(view, _decision(self.name, view, best, forced=True, stay_value=None,
                                                      reasons=["mission start: the base station's best static plan"]))
        network = view.stay_network()
        stay_valid = view.stay_valid()
        allocation = dict(view.current)
        reasons: list[str] = []
        for members in subgroups(network):
            proposal = subgroup_reallocation(
                state.scenario, network, members, allocation, view.energies, accounting=view.accounting,
                disabled_chains=frozenset(state.disabled_chains), migration=state.migration, min_gain=self.min_gain,
                min_gain_s=self.min_gain_s)
            if proposal.changes_anything:
                allocation = dict(proposal.allocation)
                reasons.extend(proposal.reasons)
        allocation = {s: h for s, h in allocation.items() if s in view.stages}
        option = view.value(network, allocation, "subgroups")
        stay_value = view.stay().value_s if stay_valid else None
        if option.value_s == -NEVER:
            best = view.best_static()
            if best is None or stay_valid:
                if stay_valid:
                    return None
                raise _no_placement(view)
            return self._with_revisit(view, _decision(
                self.name, view, best, forced=True, stay_value=None,
                reasons=[_forced_reason(view), "no subgroup could repair it alone: the base station replanned"]))
        stopped = [s for s in state.allocation if s not in allocation]
        if allocation == view.current and not stopped and stay_valid:
            return self._with_revisit(view, None, option.value_s)
        if not stay_valid:
            reasons.insert(0, _forced_reason(view))
        return self._with_revisit(view, _decision(self.name, view, option, reasons=reasons, forced=not stay_valid,
                                                  stay_value=stay_value))

    def _with_revisit(self, view: _View, decision: Decision | None, horizon_s: float | None = None) -> Decision | None:
        horizon = decision.predicted_lifetime_s if decision is not None else horizon_s
        if horizon is None or not math.isfinite(horizon) or horizon <= 0:
            return decision
        # a fixed fraction of the whole mission (not of what is left): ~1/fraction checks in all
        at = view.state.time_s + max(self.min_recheck_s, self.recheck_fraction * (view.state.time_s + horizon))
        if decision is None:
            stay = view.value(view.stay_network(), view.current, "stay")
            decision = _decision(self.name, view, stay, reasons=[], forced=False, stay_value=stay.value_s)
        return dataclasses.replace(decision, revisit_at_s=at)


POLICY_NAMES = ("static", "reactive", "rebalance", "subgroup")
_POLICIES = {"static": StaticPolicy, "reactive": ReactivePolicy, "rebalance": RebalancePolicy,
             "subgroup": SubgroupPolicy}


def make_policy(name: str, **params) -> Policy:
    """A policy by name (``static``, ``reactive``, ``rebalance``, ``subgroup``) with its parameters."""
    try:
        cls = _POLICIES[name]
    except KeyError:
        raise AutoPowerError(f"unknown policy {name!r}; choose one of {', '.join(POLICY_NAMES)}") from None
    try:
        return cls(**params)
    except TypeError as exc:
        raise AutoPowerError(f"policy {name}: {exc}") from None
