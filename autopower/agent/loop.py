"""The event queue every AutoPower process runs on.

Transport callbacks (Zenoh's threads) and signal handlers only `post` a typed event; the
process's single loop takes them one at a time, so all state is touched by one thread.
"""

from __future__ import annotations

import queue
from dataclasses import dataclass

from autopower.bus import Request


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


class EventQueue:
    """A thread-safe FIFO of `Event`s, with the callbacks the Bus needs."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue[Event] = queue.SimpleQueue()

    def post(self, event: Event) -> None:
        self._queue.put(event)

    def get(self, timeout_s: float | None) -> Event | None:
        try:
            if timeout_s is not None and timeout_s <= 0:
                return self._queue.get_nowait()
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def depth(self) -> int:
        return self._queue.qsize()

    # Bus callbacks: enqueue and return, nothing else.
    def on_message(self, key: str, payload: bytes) -> None:
        self._queue.put(Received(key, payload))

    def on_liveliness(self, key: str, alive: bool) -> None:
        self._queue.put(LivelinessChanged(key, alive))

    def on_request(self, request: Request) -> None:
        self._queue.put(OperatorRequest(request))
