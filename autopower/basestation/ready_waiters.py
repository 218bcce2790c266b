"""Operator queries held until the team is ready (`SnapshotRequest.until_ready_s`).

`up` and the demo wait for the team to get ready after they start it. Asked by polling, the base
station built, encoded and sent a snapshot of the whole team every few tens of milliseconds (about
15 ms of its loop each at 30 robots) while it was busiest: placing the mission's first plan. Held,
one query waits and is answered in the loop pass where the team gets ready, so the ready time
read is the base station's own, not a poll's.

Rules:
- a query is answered once: when the team is ready, when its wait has passed, or when the base
  station stops (with the snapshot as it is then);
- at most `MAX_HELD` queries are held; another is answered at once, so an operator (or an
  attacker with an operator's certificate) cannot make the base station keep an unbounded list.
"""

from __future__ import annotations

from dataclasses import dataclass

from autopower.runtime.bus import Request

MAX_HELD = 8


@dataclass(frozen=True)
class Held:
    request: Request
    until_unix: float  # answered at this time if the team is not ready by then


class ReadyWaiters:
    """The queries waiting for the team to get ready, in the order they came."""

    def __init__(self) -> None:
        self._held: list[Held] = []

    def __len__(self) -> int:
        return len(self._held)

    def hold(self, request: Request, until_unix: float) -> bool:
        """Keep ``request`` until the team is ready or ``until_unix``; False when full (answer it now)."""
        if len(self._held) >= MAX_HELD:
            return False
        self._held.append(Held(request, until_unix))
        return True

    def due(self, ready: bool, now_unix: float) -> list[Request]:
        """The queries to answer now (all of them once the team is ready), no longer held."""
        if ready:
            return self.take_all()
        out = [h.request for h in self._held if h.until_unix <= now_unix]
        self._held = [h for h in self._held if h.until_unix > now_unix]
        return out

    def take_all(self) -> list[Request]:
        """Every query still held (the base station stops: each gets the snapshot as it is)."""
        out, self._held = [h.request for h in self._held], []
        return out

    def next_deadline(self) -> float | None:
        """When the loop must wake to answer a query whose wait has passed (wall time)."""
        return min((h.until_unix for h in self._held), default=None)
