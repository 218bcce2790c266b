"""The typed events and the event queue every AutoPower process (agent, base station) runs on.

Transport callbacks (Zenoh's threads) and signal handlers only `post` a typed event; the
process's single loop takes them one at a time, so all state is touched by one thread.

Chain data is *bulk*: under overload it can pile up by the thousand. Everything else (control,
plans, liveliness, operator queries, stop) is *urgent* and is taken first, so an overloaded
node still answers the operator, obeys migrations and stops on Ctrl-C.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Iterable

from autopower.runtime.bus import Request


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


Event = Received | LivelinessChanged | OperatorRequest | StopRequested


SIGNAL_SLICE_S = 0.1


class EventQueue:
    """A thread-safe two-level FIFO of `Event`s, with the callbacks the Bus needs."""

    def __init__(self, bulk_keys: Iterable[str] = ()) -> None:
        # Re-entrant: a signal handler may post while the loop's thread holds the lock.
        self._cond = threading.Condition(threading.RLock())
        self._urgent: deque[Event] = deque()
        self._bulk: deque[Event] = deque()
        self.bulk_keys = set(bulk_keys)

    def post(self, event: Event, *, bulk: bool = False) -> None:
        with self._cond:
            (self._bulk if bulk else self._urgent).append(event)
            self._cond.notify()

    def get(self, timeout_s: float | None) -> Event | None:
        """The next event, urgent ones first; None after ``timeout_s`` without any."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while not (self._urgent or self._bulk):
                left = SIGNAL_SLICE_S if deadline is None else min(SIGNAL_SLICE_S, deadline - time.monotonic())
                if left <= 0:
                    break
                # Short slices: a signal that lands on a transport thread only runs its Python
                # handler when this thread returns to the interpreter.
                self._cond.wait(left)
            if self._urgent:
                return self._urgent.popleft()
            if self._bulk:
                return self._bulk.popleft()
            return None

    def depth(self) -> int:
        return len(self._urgent) + len(self._bulk)

    # Bus callbacks: enqueue and return, nothing else.
    def on_message(self, key: str, payload: bytes) -> None:
        self.post(Received(key, payload), bulk=key in self.bulk_keys)

    def on_liveliness(self, key: str, alive: bool) -> None:
        self.post(LivelinessChanged(key, alive))

    def on_request(self, request: Request) -> None:
        self.post(OperatorRequest(request))
