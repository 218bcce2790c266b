"""The team as a policy sees it, and a policy's answer.

`TeamState` is everything a policy may know (mission time, network in use, what runs, batteries,
events); `Decision` is what it answers (allocation, media, moves with their cost, reasons,
schedule). Helpers here derive the networks a state allows and price migrations.
"""


from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Mapping, Protocol, Sequence

from autopower.model.energy import airtime_s
from autopower.model.mission_events import MissionEvent
from autopower.model.network import Network, build_network, media_choices
from autopower.model.scenario import Chain, Scenario

EXHAUSTIVE_UP_TO = 20_000  # combinations (all media) enumerated exactly; beyond, the MILP decides
NEVER = math.inf
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
    # Whether the search proved `allocation` and `network` the best configuration the policy may
    # choose: None, the policy claims nothing (a heuristic, or it keeps what runs); False, it did
    # not (a MILP stopped at its time limit, or only the hosts near each chain were searched),
    # and `mip_gap` says how far from proven it is over the hosts it searched (None: unknown).
    proven_optimal: bool | None = None
    mip_gap: float | None = None

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
            air = airtime_s(size, radio, scenario.link_loss(u, v))
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

