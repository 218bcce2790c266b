"""Running component code with a time limit, off the event loop's thread.

A component is code the node does not control: it may raise, return garbage or never return.
The first two are caught where it is called (`frames.py`, `hosting.py`); this module handles the
third. Every call into a component (``run``, ``export_state``, ``import_state``) goes to one
worker thread of the node, and the loop waits for it at most ``timeout_s`` (see `hang_limit_s`).
A call that has not returned by then is declared hung: the node stops using the component and
that worker, and starts a new worker for the next call.

What this does not do, because Python cannot: kill the hung thread. It is a daemon thread and
is abandoned; if it is blocked (a lock, a socket, a sleep) it costs nothing but memory; if it
spins, it keeps using CPU until the process ends. Meanwhile the node's loop was stalled for the
time limit once, not for ever. Put a component that might spin in its own process.
"""

from __future__ import annotations

import queue
import threading
from typing import Any, Callable

HANG_PERIODS = 3  # a component call that takes longer than this many of its chain's periods has hung...
HANG_MIN_WALL_S = 2.0  # ...and longer than this many wall seconds (a loaded machine is not a hang)


def hang_limit_s(period_s: float, speed: float) -> float:
    """Wall seconds a component call of a chain with ``period_s`` may take at mission ``speed``."""
    return max(HANG_PERIODS * period_s / speed, HANG_MIN_WALL_S)


class ComponentHung(Exception):
    """A component call did not return within its time limit (its thread is abandoned)."""


class GuardedCalls:
    """Calls into components on a worker thread, waiting at most a time limit for each."""

    def __init__(self, name: str = "component"):
        self._name = name
        self._jobs: queue.SimpleQueue | None = None
        self.abandoned = 0  # workers left behind in a hung call

    def call(self, fn: Callable[..., Any], *args: Any, timeout_s: float) -> Any:
        """``fn(*args)``'s result or exception; `ComponentHung` after ``timeout_s`` wall seconds."""
        if self._jobs is None:
            self._jobs = queue.SimpleQueue()
            threading.Thread(target=_work, args=(self._jobs,), daemon=True,
                             name=f"autopower-{self._name}-{self.abandoned}").start()
        done = threading.Event()
        outcome: list = []
        self._jobs.put((fn, args, outcome, done))
        if not done.wait(timeout_s):
            self._jobs.put(None)  # the worker leaves if its call ever returns
            self._jobs = None
            self.abandoned += 1
            raise ComponentHung(f"no result after {timeout_s:.3g} s")
        ok, value = outcome[0]
        if not ok:
            raise value
        return value

    def close(self) -> None:
        if self._jobs is not None:
            self._jobs.put(None)
            self._jobs = None


def _work(jobs: queue.SimpleQueue) -> None:
    while True:
        job = jobs.get()
        if job is None:
            return
        fn, args, outcome, done = job
        try:
            outcome.append((True, fn(*args)))
        except BaseException as exc:  # handed to the caller, who decides
            outcome.append((False, exc))
        done.set()
