"""A scenario: the complete description of one mission, as frozen dataclasses.

`autopower.model.loading` builds one from a TOML file and validates it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from autopower.errors import ScenarioError
from autopower.model.control_plane import OFF, ControlPlaneSpec
from autopower.model.dag import Flow

ACCOUNTING_MODES = ("paper", "physical")
TOPOLOGIES = ("fully-connected", "relay", "explicit")
LAPTOP_ROBOT = "laptop-robot"
ROBOT_ROBOT = "robot-robot"


@dataclass(frozen=True, kw_only=True)
class Platform:
    name: str
    idle_w: float
    busy_w: float
    mains: bool = False  # mains-powered nodes (the base station) pay no energy
    levels: tuple = ()  # DVFS frequency levels (model.dvfs.FrequencyLevel); () = one fixed level
    # how many times slower than the computer running AutoPower this platform runs code: the
    # runtime's own CPU there is charged as that many seconds busy; None: measured, not charged
    slowdown: float | None = None


@dataclass(frozen=True, kw_only=True)
class Radio:
    name: str
    kbps: float
    sleep_w: float
    send_w: float
    receive_w: float


@dataclass(frozen=True, kw_only=True)
class Robot:
    name: str
    platform: str
    energy_j: float
    sensors: frozenset[str] = frozenset()


@dataclass(frozen=True, kw_only=True)
class ComponentSpec:
    name: str
    latency_s: Mapping[str, float]  # platform name -> seconds per run
    # a plug-in (see docs/tutorials/own-component.md): "pkg.mod:Class" of the component and of its
    # chain's source; None: a built-in type or one an installed package registers (entry point)
    implementation: str | None = None
    source: str | None = None
    defined_at: Mapping[str, str] = field(default_factory=dict)  # key -> "file:line", for import errors
    variants: tuple = ()  # quality variants (model.variants.Variant); () = the component as declared


@dataclass(frozen=True, kw_only=True)
class Stage:
    name: str  # the placement unit: "Loc-1"
    component: str  # the component type: "Loc"
    pin: str | None = None  # must run on this node
    hosts: tuple[str, ...] | None = None  # may run only on these nodes


@dataclass(frozen=True, kw_only=True)
class Chain:
    name: str
    source: str  # robot whose sensor feeds the chain
    sink: str  # node that consumes the result (a robot, or the base station = operator)
    period_s: float
    stages: tuple[Stage, ...]
    message_bytes: tuple[int, ...]  # source->stage0, stage0->stage1, ..., last stage->sink
    requires: frozenset[str] = frozenset()  # sensors the source robot must carry
    min_quality: float = 0.0  # the least quality score a variant may have to run this chain
    # DAG (autopower.model.dag): flows from other chains' stages into this chain's stages (fan-in);
    # sourced=False: no sensor source, the first stage is fed by its flows only (source = sink node,
    # message_bytes[0] = 0)
    inputs: tuple[Flow, ...] = ()
    sourced: bool = True
    # what a node cut off from the sink holds of its results: "all" (within the hold budget) or
    # "latest" (the newest only; the older ones are superseded: `Holds.hold`)
    keep: str = "all"


@dataclass(frozen=True, kw_only=True)
class LinkSpec:
    a: str
    b: str
    media: tuple[str, ...]  # candidate media; the first is the default
    group: str  # links in one group always share one medium choice


@dataclass(frozen=True, kw_only=True)
class CliqueSpec:
    """Every pair of `nodes` linked, all with one medium choice: a fully connected fleet's robots
    (n^2/2 links a planner never needs one by one)."""

    nodes: tuple[str, ...]
    media: tuple[str, ...]
    group: str

    def pairs(self) -> list[LinkSpec]:
        return [LinkSpec(a=a, b=b, media=self.media, group=self.group)
                for i, a in enumerate(self.nodes) for b in self.nodes[i + 1:]]


@dataclass(frozen=True, kw_only=True)
class NetworkSpec:
    topology: str
    relay: str | None = None
    laptop_robot_media: tuple[str, ...] = ()
    robot_robot_media: tuple[str, ...] = ()
    links: tuple[LinkSpec, ...] = ()  # only for topology = "explicit"
    analyze_topologies: tuple[str, ...] = ()
    # [network] loss: the share of packets a link (a pair of nodes, either direction, whatever its
    # medium) loses, 0 <= loss < 1; a pair not listed loses nothing (see model.energy.airtime_s)
    loss: Mapping[frozenset[str], float] = field(default_factory=dict)


@dataclass(frozen=True, kw_only=True)
class ReferenceRow:
    """A configuration the source paper tabulates, kept to compare against."""

    topology: str
    laptop_robot: str | None  # named topologies: the two media groups
    robot_robot: str | None
    allocation: Mapping[str, str]
    paper_lifetime_s: float | None = None
    media: Mapping[str, str] = field(default_factory=dict)  # explicit topologies: group -> medium

    def media_by_group(self) -> dict[str, str]:
        if self.topology == "explicit":
            return dict(self.media)
        return {LAPTOP_ROBOT: self.laptop_robot, ROBOT_ROBOT: self.robot_robot}


@dataclass(frozen=True, kw_only=True)
class Scenario:
    name: str
    description: str
    source_path: str
    accounting: str
    lifetime_rounding_s: float
    platforms: Mapping[str, Platform]
    radios: Mapping[str, Radio]
    robots: tuple[Robot, ...]
    basestation: str
    basestation_platform: str
    network_spec: NetworkSpec
    components: Mapping[str, ComponentSpec]
    chains: tuple[Chain, ...]
    reference_rows: tuple[ReferenceRow, ...] = ()
    migration: Mapping[str, Any] = field(default_factory=dict)  # downtime_s, cpu_s, state_bytes_default, state_bytes
    # [basestation] limit_radios: its radios may be at most 100 % busy like a robot's (off: the paper)
    basestation_radio_limit: bool = False
    # [mission] quality_weight: 0 = lifetime only, 1 = quality only (see model.variants)
    quality_weight: float = 0.0
    # [delivery] hold_budget_mb, in bytes: results a node keeps for a sink out of reach (`node.custody`)
    hold_budget_bytes: int = 64 * 2**20
    # [control_plane]: the team's own statuses and keep-alives, charged when enabled (`model.control_plane`)
    control_plane: ControlPlaneSpec = OFF

    # ---- lookups -------------------------------------------------------------------------
    def node_names(self) -> list[str]:
        return [r.name for r in self.robots] + [self.basestation]

    def robot(self, name: str) -> Robot:
        for r in self.robots:
            if r.name == name:
                return r
        raise ScenarioError(
            f"{self.source_path}: unknown robot {name!r}; the scenario has "
            f"{', '.join(r.name for r in self.robots)}"
        )

    def link_loss(self, a: str, b: str) -> float:
        """The share of packets the link between nodes a and b loses ([network] loss; 0 when not given)."""
        loss = self.network_spec.loss
        return loss.get(frozenset((a, b)), 0.0) if loss else 0.0

    def platform_of(self, node: str) -> Platform:
        if node == self.basestation:
            return self.platforms[self.basestation_platform]
        return self.platforms[self.robot(node).platform]

    def chain(self, name: str) -> Chain:
        for c in self.chains:
            if c.name == name:
                return c
        raise ScenarioError(
            f"{self.source_path}: unknown chain {name!r}; the scenario has "
            f"{', '.join(c.name for c in self.chains)}"
        )

    def stage_names(self) -> list[str]:
        return [s.name for c in self.chains for s in c.stages]

    def energies_j(self) -> dict[str, float]:
        return {r.name: r.energy_j for r in self.robots}

    # ---- derived scenarios ---------------------------------------------------------------
    def with_energies(self, energies_j: Mapping[str, float]) -> "Scenario":
        """A copy with some robots' starting energy replaced (e.g. ``--energy r1=32000``)."""
        for name, joules in energies_j.items():
            self.robot(name)  # unknown robot -> ScenarioError
            if not 0 < joules < math.inf:
                raise ScenarioError(f"energy for {name} must be > 0 J (and finite), got {joules}")
        robots = tuple(
            dataclasses.replace(r, energy_j=float(energies_j.get(r.name, r.energy_j)))
            for r in self.robots
        )
        return dataclasses.replace(self, robots=robots)

    def with_accounting(self, accounting: str | None) -> "Scenario":
        if accounting is None:
            return self
        if accounting not in ACCOUNTING_MODES:
            raise ScenarioError(
                f"accounting must be one of {', '.join(ACCOUNTING_MODES)}, got {accounting!r}"
            )
        return dataclasses.replace(self, accounting=accounting)

    def with_control_plane(self, enabled: bool | None) -> "Scenario":
        """The team's own statuses and keep-alives charged (`model.control_plane`) or not; None: as is."""
        if enabled is None:
            return self
        return dataclasses.replace(self, control_plane=dataclasses.replace(self.control_plane, enabled=enabled))

    def with_latencies(self, measured: Mapping[str, Any], platform: str, where: str) -> "Scenario":
        """A copy whose components run on `platform` with measured latencies (seconds per run, by
        component type; types the measurement lacks keep theirs). `where` names the measurement."""
        if platform not in self.platforms:
            raise ScenarioError(f"--as-platform {platform!r}: the scenario has platforms "
                                f"{', '.join(self.platforms)}")
        components = dict(self.components)
        for name, seconds in measured.items():
            if name not in components:
                continue  # a profile may cover more component types than this mission uses
            if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not 0 < seconds < math.inf:
                raise ScenarioError(f"{where}: latency_s.{name}: found {seconds!r}; expected a finite number > 0")
            spec = components[name]
            components[name] = dataclasses.replace(spec, latency_s={**spec.latency_s, platform: float(seconds)})
        return dataclasses.replace(self, components=components)

    def link_specs(self, topology: str | None = None) -> tuple[LinkSpec, ...]:
        """The links of a topology, each with its candidate media and choice group."""
        links, cliques = self.link_layout(topology)
        return links + tuple(spec for clique in cliques for spec in clique.pairs())

    def link_layout(self, topology: str | None = None) -> tuple[tuple[LinkSpec, ...], tuple[CliqueSpec, ...]]:
        """The links of a topology as single links plus cliques (the robots, linked pairwise);
        `link_specs` lists them all, in this order."""
        spec = self.network_spec
        topology = topology or spec.topology
        robots = tuple(r.name for r in self.robots)
        base = self.basestation
        if topology == "fully-connected":
            up = [LinkSpec(a=r, b=base, media=spec.laptop_robot_media, group=LAPTOP_ROBOT) for r in robots]
        elif topology == "relay":
            relay = spec.relay or robots[0]
            up = [LinkSpec(a=relay, b=base, media=spec.laptop_robot_media, group=LAPTOP_ROBOT)]
        elif topology == "explicit":
            return tuple(spec.links), ()
        else:
            raise ScenarioError(
                f"{self.source_path}: unknown topology {topology!r}; expected one of "
                f"{', '.join(TOPOLOGIES)}"
            )
        return tuple(up), (CliqueSpec(nodes=robots, media=spec.robot_robot_media, group=ROBOT_ROBOT),)


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


