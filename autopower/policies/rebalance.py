"""The rebalance policy: model-predictive time sharing on the time-sharing LP, with hysteresis.
"""


from __future__ import annotations

import dataclasses
import math
from typing import Mapping

import numpy as np

from autopower.errors import AutoPowerError
from autopower.model.network import Network
from autopower.planner.lp import INF, LinearProgram
from autopower.policies.search import DecisionView, Option, forced_reason, make_decision, no_placement, what_happened
from autopower.policies.team import NEVER, Decision, Move, SchedulePhase, TeamState, beats, plan_moves, total_energy


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
        view = DecisionView(state)
        stay = view.stay()
        best = view.best_static()
        if best is None and stay is None:
            raise no_placement(view)
        sched = self._schedule_option(view, best, stay)
        if sched is not None and best is not None and not beats(sched.value_s, best.value_s, self.min_gain,
                                                                   self.min_gain_s):
            # a schedule that barely beats the best fixed configuration is not worth its switches:
            # its predicted few seconds are within what a switch can cost beyond the model
            sched = None
        options = [o for o in (best, sched) if o is not None]
        choice = max(options, key=lambda o: o.value_s) if options else stay
        if stay is None:
            return self._emit(view, choice, stay, forced=True, why=forced_reason(view))
        stopped = [s for s in state.allocation if s not in view.stages]
        same = _same_config(view, choice, stay)
        if same and choice.schedule:
            # the schedule starts with what runs now: nothing moves, come back when its phase ends
            return self._emit(view, choice, stay, forced=False,
                              why=f"stopping {', '.join(stopped)}" if stopped else "", quiet=not stopped)
        if beats(choice.value_s, stay.value_s, self.min_gain, self.min_gain_s) and not same:
            what = what_happened(state)
            return self._emit(view, choice, stay, forced=False,
                              why=(f"after {what}: " if what else "") + "rebalancing")
        # Staying is (within the hysteresis) as good as any schedule from here: following it to the
        # end keeps it so, since the LP from later energies on this path has the same optimum.
        if stopped:
            return make_decision(self.name, view, stay, forced=False, stay_value=stay.value_s,
                             reasons=[f"stopping {', '.join(stopped)}"])
        return None

    # ---- the time-sharing schedule from the remaining energies ----------------------------------
    def _schedule_option(self, view: DecisionView, best: Option | None, stay: Option | None) -> Option | None:
        from autopower.planner.timesharing import enumerable, time_sharing_bound

        # A decision must not hold the coordinator up: a team too large to enumerate would take a
        # pricing MILP per round (66 s for 30 robots with cameras), so it plans the best fixed
        # configuration at each decision, and the periodic replans follow the batteries instead.
        if not view.problem.chains or not enumerable(view.problem):
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

    def _emit(self, view: DecisionView, choice: Option, stay: Option | None, *, forced: bool, why: str,
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
            return make_decision(self.name, view, dataclasses.replace(choice, network=first.network,
                                                                  allocation=dict(first.allocation)),
                             reasons=reasons, forced=forced, stay_value=stay_value, schedule=rest,
                             revisit_at_s=state.time_s + first.duration_s, predicted_s=choice.value_s)
        if not quiet:
            reasons.append(("the best single configuration" if choice.proven is not False else
                            f"the best single configuration found (not proven optimal: {choice.not_proven})")
                           + f": predicted {choice.value_s:,.0f} s"
                           + ("" if stay is None else f" vs {stay.value_s:,.0f} s staying"))
        return make_decision(self.name, view, choice, reasons=reasons, forced=forced, stay_value=stay_value)


def _same_config(view: DecisionView, option: Option, stay: Option) -> bool:
    first_net = option.schedule[0].network if option.schedule else option.network
    first_alloc = option.schedule[0].allocation if option.schedule else option.allocation
    return first_net == stay.network and dict(first_alloc) == dict(stay.allocation)




def _restricted_lp(view: DecisionView, phases: list[tuple[Network, dict[str, str]]]) -> list[float]:
    """Durations maximising the total over these configurations only (the time-sharing LP)."""
    powers = [view.power(n, a)[0] for n, a in phases]
    lp = LinearProgram()
    cols = [lp.var(0.0, INF, cost=-1.0) for _ in phases]
    for i in range(len(view.robots)):
        lp.row({c: float(p[i]) for c, p in zip(cols, powers, strict=True)}, -INF, float(view.energy[i]))
    sol = lp.solve()
    if not sol.has_solution:  # pragma: no cover - the LP is always feasible (t = 0)
        return [0.0] * len(phases)
    return [float(v) for v in sol.values]


def _order_phases(view: DecisionView, phases: list[tuple[Network, dict[str, str]]], durations: list[float]) -> list[int]:
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


def _schedule_value(view: DecisionView, phases: list[tuple[Network, dict[str, str]]], durations: list[float]) -> Option:
    """Predicted remaining life following these phases in order, migrations paid."""
    energy = view.energy.copy()
    prev = view.current
    total = 0.0
    out: list[SchedulePhase] = []
    first_moves: list[Move] = []
    for k, ((network, allocation), duration) in enumerate(zip(phases, durations, strict=False)):
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
    return Option(first.network, dict(first.allocation), total, first_moves, 0.0, "schedule", out)


