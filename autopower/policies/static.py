"""The static policy: the best fixed plan, repaired only when an event forces it.
"""


from __future__ import annotations

from autopower.policies.search import DecisionView, forced_reason, make_decision, no_placement, what_happened
from autopower.policies.team import NEVER, Decision, TeamState


class StaticPolicy:
    """The best fixed plan; on a forced change: local repair, then all-local, then the optimum."""

    name = "static"

    def decide(self, state: TeamState) -> Decision | None:
        view = DecisionView(state)
        if not state.allocation:
            best = view.best_static()
            if best is None:
                raise no_placement(view)
            return make_decision(self.name, view, best, reasons=["mission start: the best static plan"],
                             forced=True, stay_value=None)
        if view.stay_valid():
            stopped = [s for s in state.allocation if s not in view.stages]
            if not stopped:
                return None
            option = view.value(view.stay_network(), view.current, "stay")
            return make_decision(self.name, view, option, reasons=[f"stopping {', '.join(stopped)}: "
                                                               + (what_happened(state) or "chain no longer runs")],
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
        reason = forced_reason(view)
        option = view.value(network, repair, "repair")
        if option.value_s > -NEVER:
            return make_decision(self.name, view, option, forced=True, stay_value=None,
                             reasons=[reason, "static: stages that lost their host run locally"])
        local = {s.name: (c.source if c.source in view.problem.hosts[s.name] else view.problem.hosts[s.name][0])
                 for c in view.problem.chains for s in c.stages}
        option = view.value(network, local, "all-local")
        if option.value_s > -NEVER:
            return make_decision(self.name, view, option, forced=True, stay_value=None,
                             reasons=[reason, "static: reverting to the all-local configuration (the paper's "
                                              "baseline), since keeping the plan is infeasible"])
        best = view.best_static()
        if best is None:
            raise no_placement(view)
        return make_decision(self.name, view, best, forced=True, stay_value=None,
                         reasons=[reason, "static: even all-local is infeasible; switching to the optimum"])


