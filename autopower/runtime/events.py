"""The typed events and the event queue every AutoPower process (agent, base station) runs on.

Transport callbacks (Zenoh's threads) and signal handlers only `post` a typed event; the
process's single loop takes them one at a time, so all state is touched by one thread.

Chain data is *bulk*: under overload it can pile up by the thousand. Everything else (control,
plans, liveliness, operator queries, stop) is *urgent* and is taken first, so an overloaded
node still answers the operator, obeys migrations and stops on Ctrl-C.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Iterable

from autopower.runtime.bus import Request

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Received:
    key: str
    payload: bytes


@dataclass(frozen=True)
class LivelinessChanged:
    key: str
    alive: bool


@dataclass(frozen=True)
class OperatorRequest:
    request: Request


@dataclass(frozen=True)
class StopRequested:
    reason: str


@dataclass(frozen=True)
class WorkDone:
    """Work handed to another process finished (a stage worker's result waits to be collected)."""


@dataclass(frozen=True)
class DecisionAnswered:
    """The policy, deciding on a thread, answered: the loop's next timer carries the answer out."""


Event = Received | LivelinessChanged | OperatorRequest | StopRequested | WorkDone | DecisionAnswered


SIGNAL_SLICE_S = 0.1


# What a queue may hold before it refuses messages: a flood (of garbage or of real data faster
# than the loop takes it) must cost a bounded amount of memory, not grow until the OOM killer.
# 128 MB of bulk is ~7 s of two 4 Hz camera chains at 10x; control messages are small.
BULK_LIMIT = (100_000, 128 * 2**20)  # events, payload bytes
URGENT_LIMIT = (20_000, 32 * 2**20)
DROP_LOG_EVERY_S = 10.0


class EventQueue:
    """A thread-safe two-level FIFO of `Event`s, with the callbacks the Bus needs.

    Each level is bounded in events and in payload bytes; a message that does not fit is
    dropped (counted in `dropped`, logged at most every few seconds). Stop requests are never
    dropped. With ``admit``, a message it refuses (random bytes, not one of ours) is dropped
    before it takes any room (counted in `rejected`, logged the same way).
    """

    def __init__(self, bulk_keys: Iterable[str] = (), *, bulk_limit: tuple[int, int] = BULK_LIMIT,
                 urgent_limit: tuple[int, int] = URGENT_LIMIT,
                 admit: Callable[[bytes], bool] | None = None,
                 newest_only: Callable[[str, bytes], object] | None = None) -> None:
        """``newest_only(key, payload)`` true: that message replaces the one still queued on its key
        (a status's change from a whole one says all its older ones said), so a loop that falls
        behind finds one status per sender, not a backlog that crowds out the orders (counted in
        `superseded`). A message it is false for is queued in order, never replaced (a whole status)."""
        # Re-entrant: a signal handler may post while the loop's thread holds the lock.
        self._cond = threading.Condition(threading.RLock())
        self._urgent: deque[Event] = deque()
        self._newest: dict[str, Received] = {}  # key -> its newest message, in the order keys first came
        self._newest_only = newest_only
        self.superseded = 0
        self._bulk: deque[Event] = deque()
        self._bulk_since: deque[float] = deque()  # when each bulk event was queued (monotonic), in step
        self._bytes = {False: 0, True: 0}  # payload bytes queued, by bulk
        self._limits = {False: urgent_limit, True: bulk_limit}
        self.bulk_keys = set(bulk_keys)
        self.dropped = 0
        self._drop_logged_at = -math.inf
        self._admit = admit
        self.rejected = 0
        self._reject_logged_at = -math.inf
        # how long `get` waits at a time: short unless `wake_on_signals` makes signals wake it
        self._slice_s: float | None = SIGNAL_SLICE_S
        self._nudged = False

    def post(self, event: Event, *, bulk: bool = False) -> None:
        size = len(event.payload) if isinstance(event, Received) else 0
        newest = (not bulk and isinstance(event, Received) and self._newest_only is not None
                  and bool(self._newest_only(event.key, event.payload)))
        with self._cond:
            if newest and event.key in self._newest:
                self._bytes[False] += size - len(self._newest[event.key].payload)
                self._newest[event.key] = event  # keeps its place in line
                self.superseded += 1
                self._cond.notify()
                return
            queue = self._bulk if bulk else self._urgent
            max_events, max_bytes = self._limits[bulk]
            queued = len(queue) + (0 if bulk else len(self._newest))
            if not isinstance(event, StopRequested) and (
                    queued >= max_events or self._bytes[bulk] + size > max_bytes):
                self._drop(event, bulk)
                return
            if newest:
                self._newest[event.key] = event
            else:
                queue.append(event)
            if bulk:
                self._bulk_since.append(time.monotonic())
            self._bytes[bulk] += size
            self._cond.notify()

    def _drop(self, event: Event, bulk: bool) -> None:
        self.dropped += 1
        now = time.monotonic()
        if now - self._drop_logged_at >= DROP_LOG_EVERY_S:
            self._drop_logged_at = now
            log.warning("event queue full (%s): dropping %s (%d dropped so far); the process cannot keep up "
                        "with what it is sent", "bulk" if bulk else "urgent",
                        getattr(event, "key", type(event).__name__), self.dropped)

    def counts(self) -> dict[str, int]:
        """What was dropped so far, by why (for a status' errors): absolute counts, 0s left out."""
        return {k: n for k, n in (("queue-full", self.dropped), ("not-a-message", self.rejected)) if n}

    def _take(self, queue: deque, bulk: bool) -> Event:
        event = queue.popleft()
        if bulk:
            self._bulk_since.popleft()
        if isinstance(event, Received):
            self._bytes[bulk] -= len(event.payload)
        return event

    def get(self, timeout_s: float | None) -> Event | None:
        """The next event, urgent ones first; None after ``timeout_s`` without any."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not (self._urgent or self._newest or self._bulk):
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    break
                # Short slices unless signals wake us: a signal that lands on a transport thread
                # only runs its Python handler when this thread returns to the interpreter.
                if self._slice_s is not None:
                    left = self._slice_s if left is None else min(self._slice_s, left)
                self._cond.wait(left)
                if self._nudged:
                    self._nudged = False
                    break  # back to the interpreter: the signal's handler runs (and posts its event)
            if self._urgent:
                return self._take(self._urgent, False)
            if self._newest:
                event = self._newest.pop(next(iter(self._newest)))
                self._bytes[False] -= len(event.payload)
                return event
            if self._bulk:
                return self._take(self._bulk, True)
            return None

    def wake_on_signals(self) -> None:
        """Wake `get` when a signal arrives, wherever it lands; then it sleeps until its timeout.

        Call from the main thread, once its signal handlers are set. Without this, `get` wakes
        every `SIGNAL_SLICE_S` to let a handler run: ten wake-ups a second in a process at rest.
        Python writes each signal's number to the wakeup fd from its C handler, on whatever
        thread the signal lands; a small thread waits on that pipe and nudges the queue.
        """
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)

        def nudge() -> None:
            while os.read(read_fd, 64):
                with self._cond:
                    self._nudged = True
                    self._cond.notify_all()

        threading.Thread(target=nudge, name="signal-wakeup", daemon=True).start()
        self._slice_s = None

    def depth(self) -> int:
        return len(self._urgent) + len(self._newest) + len(self._bulk)

    def urgent_waiting(self) -> bool:
        """Whether urgent events (statuses, liveliness, plans) wait to be taken."""
        return bool(self._urgent or self._newest)

    def bulk_depth(self) -> int:
        return len(self._bulk)

    def bulk_wait_s(self) -> float:
        """How long the oldest bulk event has waited (0 if none does).

        The queue is a FIFO: whatever arrived before that long ago has been taken by the loop. A
        node's status says so, so that its producers do not take frames still waiting here for lost
        (`agent.custody`).
        """
        with self._cond:
            return time.monotonic() - self._bulk_since[0] if self._bulk_since else 0.0

    # Bus callbacks: enqueue and return, nothing else.
    def on_message(self, key: str, payload: bytes) -> None:
        if self._admit is not None and not self._admit(payload):
            with self._cond:
                self.rejected += 1
                now = time.monotonic()
                if now - self._reject_logged_at >= DROP_LOG_EVERY_S:
                    self._reject_logged_at = now
                    log.warning("dropping what is not an AutoPower message (on %s, %d B; %d dropped so far)",
                                key, len(payload), self.rejected)
            return
        self.post(Received(key, payload), bulk=key in self.bulk_keys)

    def on_liveliness(self, key: str, alive: bool) -> None:
        self.post(LivelinessChanged(key, alive))

    def on_request(self, request: Request) -> None:
        self.post(OperatorRequest(request))
