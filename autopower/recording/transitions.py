"""Metered energy against the model apart in reconfigurations and in steady running.

The model is a steady state: it prices each robot's placement from the moment a plan (or a
subgroup round) names it. The runtime carries a reconfiguration out over about two status periods
(wall): one for the plan and the orders to reach the robots, one for a new host's first report to
bring the inputs it lacks (custody resends on reports, not on timers). Meanwhile the inputs run
where they are: on the old host until it lets the stage go, on the new host once they reach it,
and, when the stage moves on before it caught up, wherever its state goes next (the base station,
which draws no battery). So within a reconfiguration a robot's meter and the model disagree by
design, and outside one they must agree.

Rule: a *reconfiguration window* opens at every change of any robot's model power (a new plan or
round, a restart's down time) and at every fault injected or healed, and lasts
``REACTION_STATUS_PERIODS`` status periods of wall time, in mission seconds at the run's speed-up.
The replay reports the metered energy less its overheads against the model inside the windows (what
reconfigurations shifted: `transition_j`) and outside them (`steady_error_pct`, which the demo's
test bounds at 1 %). A battery or overhead reading between two statuses is interpolated: the
power between two statuses is steady unless a window covers them.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Sequence

# The runtime's status period (`AgentConfig.status_period_s`: wall seconds between a running node's
# statuses) and how many of them a reconfiguration takes to carry out (see the module's rule).
STATUS_PERIOD_S = 0.5
REACTION_STATUS_PERIODS = 2


def reaction_s(speed: float | None) -> float:
    """How long a reconfiguration window lasts, in mission seconds (a simulation: one status period)."""
    return REACTION_STATUS_PERIODS * STATUS_PERIOD_S * (speed if speed else 1.0)


def windows(events: Iterable[float], length_s: float) -> list[tuple[float, float]]:
    """The union of ``[t, t + length_s]`` over ``events``, as sorted, disjoint intervals."""
    out: list[list[float]] = []
    for t in sorted(events):
        if out and t <= out[-1][1]:
            out[-1][1] = max(out[-1][1], t + length_s)
        else:
            out.append([t, t + length_s])
    return [(a, b) for a, b in out]


def clip(spans: Sequence[tuple[float, float]], t0: float, t1: float) -> list[tuple[float, float]]:
    """``spans`` within ``[t0, t1]``."""
    return [(max(a, t0), min(b, t1)) for a, b in spans if b > t0 and a < t1]


def at(times: Sequence[float], values: Sequence[float], t: float) -> float:
    """A cumulative reading at ``t``: linear between its samples, held beyond its ends."""
    if not times:
        return 0.0
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    i = bisect.bisect_right(times, t)
    a, b = times[i - 1], times[i]
    return values[i - 1] + (values[i] - values[i - 1]) * (t - a) / (b - a) if b > a else values[i]
