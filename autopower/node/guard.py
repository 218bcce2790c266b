"""Running component code with a time limit, off the event loop's thread.

A component is code the node does not control: it may raise, return garbage or never return.
The first two are caught where it is called (`frames.py`, `hosting.py`); this module handles the
third. Every call into a component or source (``run``, ``export_state``, ``import_state``,
``produce``) goes to one worker thread of the node, and the loop waits for it; unless the node
runs its stages in worker processes (``--stage-workers``, `workers.py`), which applies the same
hang rule to a process and kills it.

When is a call hung? Past its limit (`hang_limit_s`: 3 of the chain's periods, at least 2 s of
wall time), a call whose thread used no CPU over the last `BLOCKED_PROBE_S` is blocked (a
deadlock, a sleep, a read that never returns): hung. One that still computes is given up to
`SPIN_FACTOR` times the limit before it counts as hung too. The distinction matters on an
overloaded machine: a slow call there is starved, not hung, and still gets CPU now and then;
judging by wall time alone stopped healthy chains when other work saturated the CPUs. (Without
per-thread CPU clocks, i.e. off Unix, the wall-time limit alone decides.)

Components that ship with AutoPower (the blob finder, the localiser and their sources) are
called directly on the loop's thread instead: they are tested here, and the hand-off to a worker
costs two thread wake-ups per call: 80 us normally, but on a saturated machine (load 40 on 2
cores, measured) +1 to +3 ms median and +5 to +10 ms p90 per camera frame, 40 frames a second
at x10. What they raise or return is still checked like anyone's.

A hung call's component (or source) is not used again, nor is its worker: the next call starts
a new one. What this does not do, because Python cannot: kill the hung thread. It is a daemon
thread and is abandoned; if it is blocked it costs nothing but memory; if it spins, it keeps
using CPU until the process ends. Meanwhile the node's loop was stalled once, for the time the
verdict took (the limit plus a probe; at most `SPIN_FACTOR` limits for a spinning call). A
component that might spin belongs in a stage worker process (``--stage-workers on``), where a
hung call's process is killed.

The CPU time each call takes in its thread is added up (`component_cpu_s`): what a node's process
spends beyond it is the runtime's own (`Metering.charge_runtime`). A hung call's CPU is counted
up to the verdict; an abandoned thread that spins on is then the runtime's, which overstates it.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Callable

HANG_PERIODS = 3  # a component call that takes longer than this many of its chain's periods has hung...
HANG_MIN_WALL_S = 2.0  # ...and longer than this many wall seconds (a loaded machine is not a hang)
BLOCKED_PROBE_S = 0.5  # past the limit, a call whose thread used no CPU for this long is blocked: hung
SPIN_FACTOR = 10  # a call still computing after this many limits is hung as well
_IDLE_CPU_S = 0.001  # less CPU than this over a probe is "none" (timer ticks, a woken wait)


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
        self._cpu_clock: int | None = None  # the worker's CPU-time clock
        self.abandoned = 0  # workers left behind in a hung call
        self.component_cpu_s = 0.0  # CPU time the calls took in their threads (returned or raised)

    def call(self, fn: Callable[..., Any], *args: Any, timeout_s: float) -> Any:
        """``fn(*args)``'s result or exception; `ComponentHung` if it hangs (see the module docstring)."""
        if _ships_with_autopower(getattr(fn, "__self__", None)):
            return self.counted(fn, *args)
        if self._jobs is None:
            self._start_worker()
        started = time.monotonic()
        done = threading.Event()
        outcome: list = []
        self._jobs.put((fn, args, outcome, done))
        call_cpu_at = self._worker_cpu_s()
        finished = done.wait(timeout_s)
        while not finished:
            before = self._worker_cpu_s()
            finished = done.wait(BLOCKED_PROBE_S)
            if finished:
                break
            waited = time.monotonic() - started
            used = None if before is None else self._worker_cpu_s() - before
            if used is None or used < _IDLE_CPU_S or waited >= SPIN_FACTOR * timeout_s:
                now_cpu = self._worker_cpu_s()
                if now_cpu is not None and call_cpu_at is not None:
                    self.component_cpu_s += max(0.0, now_cpu - call_cpu_at)
                self._abandon_worker()
                how = "blocked" if used is not None and used < _IDLE_CPU_S else "still running"
                raise ComponentHung(f"no result after {waited:.3g} s ({how}; limit {timeout_s:.3g} s)")
        ok, value, cpu_s = outcome[0]
        self.component_cpu_s += cpu_s
        if not ok:
            raise value
        return value

    def counted(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` on this thread with no time limit, its CPU counted as the components'
        (building a component or source: its constructor is component code too)."""
        before = time.thread_time()
        try:
            return fn(*args)
        finally:
            self.component_cpu_s += time.thread_time() - before

    def close(self) -> None:
        if self._jobs is not None:
            self._jobs.put(None)
            self._jobs = None

    def _start_worker(self) -> None:
        self._jobs = queue.SimpleQueue()
        worker = threading.Thread(target=_work, args=(self._jobs,), daemon=True,
                                  name=f"autopower-{self._name}-{self.abandoned}")
        worker.start()
        try:
            self._cpu_clock = time.pthread_getcpuclockid(worker.ident)
        except (AttributeError, OSError):  # not on this platform: wall time alone decides
            self._cpu_clock = None

    def _worker_cpu_s(self) -> float | None:
        if self._cpu_clock is None:
            return None
        try:
            return time.clock_gettime(self._cpu_clock)
        except OSError:
            return None

    def _abandon_worker(self) -> None:
        self._jobs.put(None)  # the worker leaves if its call ever returns
        self._jobs = None
        self._cpu_clock = None
        self.abandoned += 1


def _ships_with_autopower(owner: object) -> bool:
    """Is ``owner`` (a component or source instance) one of AutoPower's own?"""
    return owner is not None and type(owner).__module__.partition(".")[0] == "autopower"


def _work(jobs: queue.SimpleQueue) -> None:
    while True:
        job = jobs.get()
        if job is None:
            return
        fn, args, outcome, done = job
        before = time.thread_time()
        try:
            result = (True, fn(*args))
        except BaseException as exc:  # handed to the caller, who decides
            result = (False, exc)
        outcome.append((*result, time.thread_time() - before))
        done.set()
