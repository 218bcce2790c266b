"""Prediction: what the model says the plan in force draws, and how the robots' batteries compare.

The prediction is made for the target placement when a plan is decided (at the DVFS levels its
placement fits in), and for the confirmed placement while stages still move (the figure each plan
carries). A robot's battery is compared with it from a baseline taken once the robot runs the plan:
a drift beyond ``drift_tolerance`` asks the policy again (`Deciding.check_drift`).
"""

from __future__ import annotations

from dataclasses import dataclass

from autopower.errors import AutoPowerError
from autopower.model.dvfs import apply_levels, best_levels, has_levels
from autopower.model.energy import evaluate
from autopower.model.network import Network
from autopower.protocol import NodeStatus


@dataclass
class Baseline:
    """A robot's battery when the plan's prediction was anchored for it, and the power the plan predicted."""

    t_virtual: float
    battery_j: float
    predicted_w: float


@dataclass(frozen=True)
class Drift:
    """A robot drew ``measured_j`` over ``elapsed_s`` where the plan predicted ``predicted_j`` (at ``predicted_w``)."""

    measured_j: float
    predicted_j: float
    elapsed_s: float
    predicted_w: float


class Prediction:
    """The coordinator's model of the plan in force: power per robot, DVFS levels, lifetime, battery baselines."""

    def __init__(self, team):
        """``team``: the `Coordinator` whose placing and deciding parts say what runs, on which network."""
        self.team = team
        self.predicted_w: dict[str, float] = {}
        self.levels: dict[str, str] = {}  # robot -> DVFS level of the current plan (`_at_levels`)
        self.predicted_lifetime_s: float | None = None
        self.plan_t_virtual = 0.0
        self.baselines: dict[str, Baseline] = {}

    def evaluate(self, allocation: dict[str, str], network: Network | None, energies: dict[str, float],
                 running: set[str] | None = None, levels: dict[str, str] | None = None):
        """The model for an allocation on the network of the nodes alive; None if it has no answer.

        ``running``: the chains that run (default: those with a stage in the allocation; given, an
        empty allocation is a team whose chains are stopped). ``levels``: DVFS levels to price at."""
        if network is None or (not allocation and running is None):
            return None
        team = self.team
        active = running if running is not None else {team.chain_of[s].name for s in allocation}
        scenario = apply_levels(team.scenario, levels) if levels else team.scenario
        disabled = frozenset(c.name for c in scenario.chains if c.name not in active)
        try:
            return evaluate(scenario, network.without_nodes(set(team.deciding.unavailable())), allocation,
                            energies_j=energies, disabled_chains=disabled)
        except AutoPowerError:
            return None

    def predict(self) -> None:
        """The prediction for the target placement on the plan's network, from the remaining energies."""
        deciding = self.team.deciding
        ev = self.evaluate(self.team.placing.target, deciding.plan_network, deciding.remaining_energies())
        ev = self._at_levels(ev)
        self.predicted_w = {r: p.steady_w for r, p in ev.robots.items()} if ev else {}
        self.predicted_lifetime_s = ev.lifetime_s if ev else None
        self.plan_t_virtual = self.team.now()
        self.reset_baselines()

    def placement_w(self) -> dict[str, float]:
        """The model's power per robot for what runs now: the confirmed placement of the chains
        that run, at the plan's DVFS levels. While stages move this is not the target's
        prediction, and a robot running a stage until its migration lands is drawing for it: the
        plan tells each robot this figure, and the robot's status carries it to the recording
        (replay checks the meter against it). {} when it cannot be evaluated."""
        team = self.team
        placing = team.placing
        placement, target, running = placing.placement, placing.target, set(placing.runs.running)
        if placement == target and running == {c.name for c in team.scenario.chains
                                                if any(s.name in target for s in c.stages)}:
            return dict(self.predicted_w)  # settled: the target's prediction is the placement's
        allocation = {s: n for s, n in placement.items() if team.chain_of[s].name in running}
        ev = self.evaluate(allocation, team.deciding.plan_network, {}, running=running, levels=self.levels)
        return {r: p.steady_w for r, p in ev.robots.items()} if ev else {}

    def _at_levels(self, ev):
        """DVFS: every robot at the cheapest frequency level at which its placement fits (a robot's
        level changes only its own power, so this is optimal for any policy's placement); the plan
        carries the levels to the agents and the prediction is made at them."""
        team = self.team
        self.levels = best_levels(team.scenario, ev.utilisation) if ev is not None and has_levels(team.scenario) else {}
        if not self.levels:
            return ev
        deciding = team.deciding
        return self.evaluate(team.placing.target, deciding.plan_network, deciding.remaining_energies(),
                             levels=self.levels)

    def reset_baselines(self) -> None:
        self.baselines.clear()  # re-anchored from the next status that reflects the settled plan

    def drift(self, status: NodeStatus, min_window_s: float, tolerance: float) -> Drift | None:
        """How far ``status``'s battery is off the prediction since its baseline, when it is off by more
        than ``tolerance`` (relative) over at least ``min_window_s``; the first status anchors the baseline."""
        if status.node not in self.predicted_w:
            return None
        base = self.baselines.get(status.node)
        if base is None:
            self.baselines[status.node] = Baseline(status.t_virtual, status.battery_j, self.predicted_w[status.node])
            return None
        elapsed = status.t_virtual - base.t_virtual
        if elapsed < min_window_s:
            return None
        predicted = base.predicted_w * elapsed
        measured = base.battery_j - status.battery_j
        if predicted > 0 and abs(measured - predicted) > tolerance * predicted:
            return Drift(measured, predicted, elapsed, base.predicted_w)
        return None
