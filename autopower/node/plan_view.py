"""The plan a node runs: the base station's (or a subgroup round's placement over it), its network and
the model's power for it.

`PlanView` is a collaborator of `NodeRuntime`. It owns the plan, the network built from its links
(the routes every frame takes), the nodes out of reach while the base station is, the model's power
once a stage has left before the plan says where it landed, and the plans' assembler (plans come as
their change from the one before, `protocol.plans`). The runtime applies a new plan to the others
(`NodeRuntime.on_plan`).
"""

from __future__ import annotations

import base64
import dataclasses
import logging

from autopower.errors import AutoPowerError
from autopower.model.network import Link, Network
from autopower.protocol import PlanUpdate, encode
from autopower.protocol.plans import PlanAssembler

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class PlanView:
    """The plan this node runs and what follows from it: routes, DVFS level, the model's power."""

    def __init__(self, rt):
        """``rt``: the `NodeRuntime` that runs the plan (its scenario, meter and stages)."""
        self.rt = rt
        self.plan: PlanUpdate | None = None
        self.network: Network | None = None
        # nodes this one does not reach while it decides without the base station (`set_out_of_reach`):
        # the model's power leaves out what cannot reach them
        self.out_of_reach: frozenset[str] = frozenset()
        # the model's power per robot once a stage has left us and before the plan says where it
        # landed (`stage_left`): we no longer run it; None: the plan's prediction holds
        self.model_override: dict[str, float] | None = None
        self.left: dict[str, str] = {}  # stage -> the node it left us for, until the next plan (`stage_left`)
        self._payload: bytes | None = None  # the last plan message handled (a repeat of it is skipped)
        self._plans = PlanAssembler()  # plans sent as their change from the one before (`protocol.plans`)
        self._text_of: tuple[PlanUpdate, str] | None = None  # (plan, its resume-state text): `text`

    def take(self, payload: bytes) -> PlanUpdate | None:
        """A plan message: the whole plan it makes, or None when it is the one handled last (plans
        only move forward: what was applied or ignored once would be ignored now) or a change from a
        plan this node does not hold (the base station resends it whole)."""
        if payload == self._payload:
            return None
        self._payload = payload
        plan = self._plans.whole(payload)
        if plan is None:
            self.rt.tally("plan-changes-skipped")
        return plan

    def remember(self, plan: PlanUpdate) -> None:
        """``plan`` is the base of the next change (the base station's host, a saved plan)."""
        self._plans.remember(plan)

    @property
    def order(self) -> tuple[int, int]:
        """(incarnation, epoch) of the plan this node runs; (-1, -1) before the first."""
        return (self.plan.incarnation, self.plan.epoch) if self.plan else (-1, -1)

    def set_plan(self, plan: PlanUpdate) -> None:
        same_links = self.plan is not None and self.network is not None and plan.links == self.plan.links
        self.plan = plan
        self.model_override = None
        self.left = {}
        if not same_links:  # most new plans move stages, not links: the routes stay (O(links) to build)
            nodes = self.rt.scenario.node_names()
            known = frozenset(nodes)
            links = [Link(a=l.a, b=l.b, medium=l.medium, group="runtime") for l in plan.links
                     if l.a in known and l.b in known and l.medium in self.rt.scenario.radios]
            self.network = Network(nodes, self.rt.scenario.basestation, links, "runtime")
        self.rt.meter.set_media(self.network.media_of(self.rt.node), self.rt.now())
        self.rt.meter.set_level(self._level(plan.levels.get(self.rt.node)), self.rt.now())

    def _level(self, name: str | None):
        """The DVFS level the plan names for this node (None: nominal; an unknown name is refused)."""
        if name is None or self.rt.platform.mains:
            return None
        level = next((lv for lv in self.rt.platform.levels if lv.name == name), None)
        if level is None:
            self.rt.count("unknown-level", f"plan names level {name[:40]!r}, the platform has "
                       f"{', '.join(lv.name for lv in self.rt.platform.levels) or 'none'}")
        return level

    def override_placement(self, placement: dict[str, str], unreachable: set[str]) -> None:
        """A placement agreed without the base station (a subgroup commit): same epoch, our view.

        Links to ``unreachable`` nodes leave the routing; the next plan from the base station
        (a higher epoch) replaces all of it.
        """
        if self.plan is None:
            return
        links = tuple(l for l in self.plan.links if l.a not in unreachable and l.b not in unreachable)
        self.set_plan(dataclasses.replace(self.plan, placement={**self.plan.placement, **placement}, links=links))
        # the base station's prediction was for its placement: say the model's for this one
        self.plan = dataclasses.replace(self.plan, predicted_w=self.predict_power())
        self.rt.hosting.placement_overridden(self.plan.placement)
        self.rt.frames.flush_held()  # a round's placement may route a held result's sink again

    def stage_left(self, stage: str, to_node: str) -> None:
        """``stage`` has left this node for ``to_node``: the model's power is priced with it there until
        the plan says where it landed."""
        self.left[stage] = to_node
        if self.plan is not None and self.plan.predicted_w:
            self.model_override = self.predict_power({**self.plan.placement, **self.left}, own_only=True)

    @property
    def model_w(self) -> float | None:
        """The model's power for what this node runs now (`NodeStatus.model_w`)."""
        if self.plan is None:
            return None
        return (self.model_override if self.model_override is not None else self.plan.predicted_w).get(self.rt.node)

    def set_out_of_reach(self, nodes: frozenset[str]) -> None:
        """The nodes this one does not reach now, while the base station is out of its reach (empty
        once it is back: its plans account for the links it knows). The model's power is priced again
        without them: a robot cut off from the source of a chain a round had put on it does not run
        that chain, and the model must not count it."""
        if nodes == self.out_of_reach:
            return
        self.out_of_reach = nodes
        if self.plan is not None and self.network is not None:
            self.plan = dataclasses.replace(self.plan, predicted_w=self.predict_power(own_only=True))

    def predict_power(self, placement: dict[str, str] | None = None, own_only: bool = False) -> dict[str, float]:
        """The model's power per robot for the plan this node runs (its placement, or the one
        given, routing and DVFS levels; a chain whose sink is out of reach buffers at its source).

        A chain with a stage out of reach of the node before it is left out: it cannot run as
        placed here (another partition's placement, seen from this one, after a subgroup round
        moved only what this one reaches). Left in, it would make the whole prediction fail, and the
        recording would keep the old plan's power for this robot while it runs its chains itself.
        {} if the model cannot price it (telemetry: never worth stopping for).

        ``own_only``: this node's power alone (its `model_w`), priced from the chains that load it
        (`_touching`), the same figure at a fraction of the cost on a large team: a node's power
        depends only on its own CPU and radios, which no other chain loads."""
        from autopower.model.dvfs import apply_levels
        from autopower.model.energy import evaluate
        from autopower.policies import effective_scenario

        plan, network = self.plan, self._network_in_reach()
        try:
            scenario = apply_levels(self.rt.scenario, dict(plan.levels)) if plan.levels else self.rt.scenario
            scenario, _ = effective_scenario(scenario, network)
            placement = {s: n for s, n in (plan.placement if placement is None else placement).items() if s in self.rt.stage_index}
            active = ({self.rt.stage_index[s][0].name for s in placement} & set(plan.running)) \
                - _unroutable(scenario.chains, network, placement)
            placement = {s: n for s, n in placement.items() if self.rt.stage_index[s][0].name in active}
            if own_only and not any(c.inputs for c in scenario.chains):  # DAG flows: every chain, as ever
                active &= _touching(scenario, network, placement, self.rt.node)
                placement = {s: n for s, n in placement.items() if self.rt.stage_index[s][0].name in active}
            disabled = frozenset(c.name for c in scenario.chains if c.name not in active)
            ev = evaluate(scenario, network, placement, accounting=plan.mission.accounting,
                          disabled_chains=disabled)
        except (AutoPowerError, KeyError, ValueError) as exc:
            log.info("%s: no model prediction for the placement %s: %s", self.rt.node, dict(plan.placement), exc)
            return {}
        if own_only:
            own = ev.robots.get(self.rt.node)
            return {} if own is None else {self.rt.node: own.steady_w}
        return {r: p.steady_w for r, p in ev.robots.items()}

    def _network_in_reach(self) -> Network:
        """The plan's network without the nodes out of reach (`set_out_of_reach`)."""
        network = self.network
        if self.out_of_reach:
            network = Network(network.nodes, network.basestation,
                              [l for l in network.links if l.a not in self.out_of_reach and l.b not in self.out_of_reach],
                              network.topology)
        return network

    def priced_here(self) -> set[str]:
        """The stages the model prices on this node (`predict_power`'s rule): placed here by the plan
        it runs, where the stages that left us since went (`stage_left`), of a chain the plan runs
        whose every hop is routable. What the simulator's oracle holds against what this node runs
        (`teamsim`'s model-runs invariant)."""
        if self.plan is None or self.network is None:
            return set()
        placement = {s: n for s, n in {**self.plan.placement, **self.left}.items() if s in self.rt.stage_index}
        here = {s for s, n in placement.items() if n == self.rt.node and self.rt.stage_index[s][0].name in self.plan.running}
        # only the chains with a stage here: checked at every status, on teams of hundreds
        chains = {self.rt.stage_index[s][0].name: self.rt.stage_index[s][0] for s in here}.values()
        stranded = _unroutable(chains, self._network_in_reach(), placement)
        return {s for s in here if self.rt.stage_index[s][0].name not in stranded}

    def text(self) -> str | None:
        """The plan we run as the resume state keeps it: encoded once per plan (a fleet's plan is
        large, and the state is saved with every status)."""
        if self.plan is None:
            return None
        if self._text_of is None or self._text_of[0] is not self.plan:
            self._text_of = (self.plan, base64.b64encode(encode(self.plan)).decode("ascii"))
        return self._text_of[1]


def _hops(chains, placement: dict[str, str]):
    """Each placed chain of ``chains`` and its hops between distinct nodes (source, each stage's host, sink)."""
    for chain in chains:
        hosts = [placement.get(stage.name) for stage in chain.stages]
        if None in hosts:
            continue
        path = [chain.source, *hosts, chain.sink]
        yield chain, [(a, b) for a, b in zip(path, path[1:], strict=False) if a != b]


def _touching(scenario, network, placement: dict[str, str], node: str) -> set[str]:
    """Chains that load ``node``: a stage placed on it, or a hop whose route sends or receives on it
    (as an end or a relay)."""
    return {chain.name for chain, hops in _hops(scenario.chains, placement)
            if any(node in (u, v) for a, b in hops for u, v, _ in network.hops(a, b))
            or node in (placement.get(s.name) for s in chain.stages)}


def _unroutable(chains, network, placement: dict[str, str]) -> set[str]:
    """The chains of ``chains`` with a hop whose ends do not reach each other."""
    return {chain.name for chain, hops in _hops(chains, placement)
            if any(not network.reachable(a, b) for a, b in hops)}
