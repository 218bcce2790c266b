"""The one event queue of a simulated team: every action happens at a virtual time, in order.

Events are ordered by (time, sequence number): two events at the same time run in the order they
were scheduled, so a run depends on nothing but its inputs. Time is the simulated wall clock in
seconds since the simulation began; `wall` gives it as unix seconds from a fixed epoch.
"""

from __future__ import annotations

import heapq
from typing import Callable

EPOCH_UNIX = 1_000_000.0  # the simulated wall clock at time 0 (any fixed value does)


class Scheduler:
    """A heap of (time, seq, action, args); `run_until` pops and runs them in order."""

    def __init__(self) -> None:
        self.now = 0.0
        self._heap: list[tuple[float, int, Callable, tuple]] = []
        self._seq = 0
        self.ran = 0

    def wall(self) -> float:
        """The simulated wall clock (unix seconds)."""
        return EPOCH_UNIX + self.now

    def at(self, t: float, action: Callable, *args) -> None:
        """Run ``action(*args)`` at time ``t`` (never before now)."""
        self._seq += 1
        heapq.heappush(self._heap, (max(t, self.now), self._seq, action, args))

    def after(self, dt: float, action: Callable, *args) -> None:
        self.at(self.now + dt, action, *args)

    def run_until(self, t_end: float) -> None:
        """Run every event due up to ``t_end``; the clock then reads ``t_end``."""
        heap = self._heap
        while heap and heap[0][0] <= t_end:
            t, _, action, args = heapq.heappop(heap)
            self.now = t
            self.ran += 1
            action(*args)
        self.now = max(self.now, t_end)
