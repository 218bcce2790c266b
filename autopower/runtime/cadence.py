"""When a node publishes its status: at once when something in it changed, else a slow heartbeat.

A status that says nothing new beyond what drifts with time (clock, battery, energy, mean power)
and what counts the work flowing through the node (frames produced, outputs received, runs,
counters) is held back until the rest period has passed since the last one: that is the slow
heartbeat, at rest and while the chains run alike. Anything else in it (a plan, a stage's state, a
generation, a link, a chain's run, a failed component) goes out at the next period, as it always did.
No node decides anything on a count (the base station reads a source's run, not how many frames
it produced); the counts are for the recording and the live table, which see them every heartbeat.
A running robot's status to the base station was most of the team's control bytes, sent every
period because a count had moved: over GSM that alone kept the radio busy a third of the time.

What flowed is still acknowledged every period (`Acknowledging.send`): custody, not the
status, needs that, and a producer's frames must not wait for the next heartbeat to be let go.

Every status announces when the next one is due (``NodeStatus.next_status_s``): a receiver's
status-silence detector waits that long, not its own period, so it neither fires at a node on the
slow heartbeat nor waits longer than needed for one that has news. The status that first finds
nothing new announces the rest period, so no receiver ever expects the short one when it is not coming.

A node's loop need not even wake to build a status that would be held back: while it rests and
nothing it does is timed (no source, no stage, nothing in custody: the loop knows), it sleeps until
the rest period ends, its peers' silence deadlines (`next_silence_s`) or an event, and builds the
status when an event comes instead of at the next tick (`StatusCadence.next_build`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

from autopower.protocol import NodeStatus

# A status not followed by the next one within this many of the periods it announced is put again,
# and again every REPEAT_EVERY_PERIODS (`Bus.repeat_until_next`), well inside the 2 periods a peer's
# silence detector waits: a loop held up by one long event is not taken for a cut link.
REPEAT_AFTER_PERIODS = 1.1
REPEAT_EVERY_PERIODS = 0.5

# What changes with time alone, also at rest: not a reason to speak before the rest period (the
# runtime's own bytes and CPU grow at rest too: keep-alives, statuses, the loop's wake-ups).
DRIFTING = {"t_virtual": 0.0, "t_unix": 0.0, "battery_j": None, "energy_j": {}, "power_w": {},
            "cpu_utilisation": 0.0, "next_status_s": 0.0, "link_bytes": (0, 0), "control_bytes": (0, 0),
            "link_packets": (0, 0),
            "runtime_cpu_s": 0.0, "component_cpu_s": 0.0}
# What counts the work that flows through the node: changes every period while a chain runs, read by
# the recording and the live table only. (A source's and a sink's run stay: a new run is news.)
FLOWING = {"runs": {}, "compute_ms": {}, "queue_depth": 0, "errors": {}, "counters": {}, "queue_wait_s": 0.0}


def steady_part(status: NodeStatus) -> NodeStatus:
    """``status`` without what drifts with time or counts what flows: what must be said at once
    when it changes (two statuses with equal steady parts say nothing new to any peer)."""
    return dataclasses.replace(status, **DRIFTING, **FLOWING,
                               sources={name: s.run for name, s in status.sources.items()},
                               sinks={name: s.run for name, s in status.sinks.items()})


class StatusCadence:
    """Decides, for each status a node builds, whether it goes out now and what it announces."""

    def __init__(self, period_s: float, rest_period_s: float):
        self.period_s = period_s
        self.rest_period_s = max(period_s, rest_period_s)
        self._last: NodeStatus | None = None  # the last status sent, drifting fields blanked
        self._last_wall: float | None = None
        self._last_announced = period_s

    @property
    def resting(self) -> bool:
        """The last status went out announcing the rest period (nothing new in it)."""
        return self._last_wall is not None and self._last_announced == self.rest_period_s

    def next_build(self, tick: float, *, quiet: bool) -> float:
        """When the loop must next build a status (wall time): at its next ``tick`` (every period),
        or, while the node rests and nothing it does is timed (``quiet``), only once the rest period
        since the last status has passed (a status built before would be held back). Whatever
        happens meanwhile comes as an event, and the loop builds one then (`due` decides)."""
        if quiet and self.resting:
            return max(tick, self._last_wall + self.rest_period_s)
        return tick

    def due(self, status: NodeStatus, now: float, *, urgent: bool = False) -> NodeStatus | None:
        """``status`` with the announcement to publish now, or None (held back: nothing new).

        ``urgent``: something the others must hear at once (a link seen or lost, a new plan): it
        goes out and announces the normal period.
        """
        steady = steady_part(status)
        unchanged = steady == self._last
        if (unchanged and not urgent and self._last_announced == self.rest_period_s and self._last_wall is not None
                and now - self._last_wall < self.rest_period_s - self.period_s / 2):
            return None
        # unchanged since the last one: the node is at rest, say the next comes after the rest period
        # (an urgent one says something changed: the normal cadence)
        announced = self.rest_period_s if unchanged and not urgent else self.period_s
        self._last, self._last_wall, self._last_announced = steady, now, announced
        return dataclasses.replace(status, next_status_s=announced)


def status_period_s(own_period_s: float, announced_s: float) -> float:
    """The status period a node is judged by: the one it announced (``announced_s``, 0 for none),
    never shorter than ours, so a node that announced none is judged by our period."""
    return max(own_period_s, announced_s)


def silence_limit_s(periods: float, own_period_s: float, announced_s: float, lease_s: float) -> float:
    """How long a node's statuses may stay away before it counts as silent (out of sight).

    ``periods`` of its status period (`status_period_s`), never sooner than the lease plus one of
    those periods: a node's loop may be held in a reliable put for up to a lease by a link of its
    own that died silently (Zenoh closes such a link only then, `runtime.bus`), and its next status
    comes within a period after that. Silence shorter than that says nothing about the link we
    hear it on.
    """
    period = status_period_s(own_period_s, announced_s)
    return max(periods * period, lease_s + period)


def next_silence_s(heard: Mapping[str, float], limits: Mapping[str, float]) -> float | None:
    """When the first of the watched nodes (``limits``: node -> its silence limit) counts as silent,
    from when each was last ``heard`` (wall times); None if none of them was heard yet.

    A loop that wakes only for its deadlines wakes for this one: a silent peer is found when its
    limit passes, not at whatever tick comes next.
    """
    return min((heard[n] + limit for n, limit in limits.items() if n in heard), default=None)
