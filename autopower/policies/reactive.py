"""The reactive policy: replan on events, move only when the move pays for itself.
"""


from __future__ import annotations

from autopower.policies.search import DecisionView, forced_reason, make_decision, no_placement, what_happened
from autopower.policies.team import Decision, TeamState, beats


class ReactivePolicy:
    """Replan on events only; move only if the new plan outlives the old one after migrations."""

    name = "reactive"

    def __init__(self, min_gain: float = 0.001, min_gain_s: float = 10.0):
        self.min_gain = min_gain
        self.min_gain_s = min_gain_s

    def decide(self, state: TeamState) -> Decision | None:
        view = DecisionView(state)
        stay = view.stay()
        if stay is not None and not state.events:
            return None
        best = view.best_static()
        if best is None:
            if stay is None:
                raise no_placement(view)
            return None
        if stay is None:
            return make_decision(self.name, view, best, forced=True, stay_value=None,
                             reasons=[forced_reason(view), "replanned from the remaining energies"])
        stopped = [s for s in state.allocation if s not in view.stages]
        if beats(best.value_s, stay.value_s, self.min_gain, self.min_gain_s):
            return make_decision(self.name, view, best, forced=False, stay_value=stay.value_s,
                             reasons=[f"after {what_happened(state)}: replanned; predicted lifetime "
                                      f"{stay.value_s:,.0f} s → {best.value_s:,.0f} s "
                                      f"({best.value_s / stay.value_s - 1:+.2%}) after migrations"])
        keep = (f"after {what_happened(state)}: " + (f"stopping {', '.join(stopped)}; " if stopped else "")
                + f"keeping the plan (the best alternative predicts {best.value_s:,.0f} s vs {stay.value_s:,.0f} s; "
                f"a move must gain {self.min_gain:.1%} + {self.min_gain_s:g} s)")
        return make_decision(self.name, view, stay, forced=False, stay_value=stay.value_s, reasons=[keep])


