"""Fig. 7-style tables: every topology x media pair, with all-local, all-laptop and the optimum."""

from __future__ import annotations

from dataclasses import dataclass

from autopower.errors import AutoPowerError, InfeasibleError
from autopower.model.energy import Evaluation, evaluate
from autopower.model.network import Network, build_network, media_choices
from autopower.model.scenario import LAPTOP_ROBOT, ROBOT_ROBOT, Scenario
from autopower.planner import PlanRequest, infeasible_error, plan
from autopower.planner.exhaustive import exhaustive
from autopower.planner.problem import make_problem


@dataclass
class Row:
    topology: str
    media: dict[str, str]
    label: str
    allocation: dict[str, str]
    evaluation: Evaluation | None  # None for an "infeasible" row: no allocation to evaluate
    paper_lifetime_s: float | None = None
    reason: str | None = None  # why an "infeasible" row has no allocation

    def to_dict(self, normaliser: float | None) -> dict:
        ev = self.evaluation
        life = ev.lifetime_rounded_s if ev else None
        return {
            "topology": self.topology,
            "laptop_robot_medium": self.media.get(LAPTOP_ROBOT),
            "robot_robot_medium": self.media.get(ROBOT_ROBOT),
            "media": dict(self.media),
            "allocation": dict(self.allocation),
            "label": self.label,
            "feasible": bool(ev and ev.feasible),
            "lifetime_s": life,
            "normalized": round(life / normaliser, 4) if (life and normaliser) else None,
            "bottleneck": ev.bottleneck if (ev and ev.feasible) else None,
            "violations": [v.message for v in ev.violations] if ev else [],
            "paper_lifetime_s": self.paper_lifetime_s,
            "reason": self.reason,
        }


def all_local(scenario: Scenario) -> dict[str, str]:
    return {s.name: (s.pin or c.source) for c in scenario.chains for s in c.stages}


def all_base(scenario: Scenario) -> dict[str, str]:
    return {s.name: (s.pin or scenario.basestation) for c in scenario.chains for s in c.stages}


def analyze(scenario: Scenario, max_ties: int = 4, method: str = "auto") -> tuple[list[Row], float | None]:
    """Rows of the table and the lifetime the "normalized" column divides by.

    Like the paper's Fig. 7, "normalized" divides by the shortest-lived feasible all-local row
    (Fig. 7's row 4, 29121.6 s).
    """
    rows: list[Row] = []
    for topology in scenario.network_spec.analyze_topologies:
        for media in media_choices(scenario, topology):
            network = build_network(scenario, topology, media)
            for label, allocation in (("all-local", all_local(scenario)), ("all-laptop", all_base(scenario))):
                rows.append(Row(topology, media, label, allocation, evaluate(scenario, network, allocation)))
            rows.extend(_optimal_rows(scenario, network, topology, media, max_ties, method))
    for i, ref in enumerate(scenario.reference_rows, start=1):
        media = ref.media_by_group()
        network = build_network(scenario, ref.topology, media)
        rows.append(Row(ref.topology, media, f"paper-row-{i}", dict(ref.allocation),
                        evaluate(scenario, network, ref.allocation), ref.paper_lifetime_s))
    local = [r.evaluation.lifetime_rounded_s for r in rows if r.label == "all-local" and r.evaluation.feasible]
    return rows, (min(local) if local else None)


def _optimal_rows(scenario: Scenario, network: Network, topology: str, media: dict, max_ties: int, method: str) -> list[Row]:
    """The optimum and its ties, or one "infeasible" row saying why; a solver failure raises.

    Only a proven answer is labelled "optimal": an infeasible media pair is reported as such
    (with the resource that breaks), and any other planner failure is an error, not a row.
    """
    request = PlanRequest(scenario=scenario, network=network, method=method, max_ties=max_ties)
    problem = make_problem(request)
    if method != "milp" and problem.combinations() <= 200_000:
        candidates = exhaustive(problem, max_ties=max_ties)
        found = [(c.allocation, c.network) for c in candidates]
        if not found:
            return [Row(topology, media, "infeasible", {}, None, reason=str(infeasible_error(problem)))]
    else:
        try:
            p = plan(request)
        except InfeasibleError as exc:
            return [Row(topology, media, "infeasible", {}, None, reason=str(exc))]
        if not p.proven_optimal:
            raise AutoPowerError(f"{topology} {media}: the MILP stopped with a gap of {p.mip_gap:.2%} "
                                 f"before proving its plan optimal; raise the time limit or use --method exhaustive")
        found = [(p.allocation, p.network)]
    out = []
    for k, (allocation, net) in enumerate(found):
        ev = evaluate(scenario, net, allocation)
        out.append(Row(topology, media, "optimal" if k == 0 else "optimal-tie", allocation, ev))
    return out
