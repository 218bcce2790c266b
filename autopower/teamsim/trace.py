"""The trace of a simulated run: every delivered message and every fault, hashed as it happens.

A record is one line: the virtual time (`repr` of the float: exact), what happened and to whom,
and for a message its key and the SHA-256 of its payload. `sha256` is the hash of all lines in
order: the same seed and build give the same hash, in any process. The lines themselves are kept
only when asked for (``keep``), for a reader looking for where two runs part.
"""

from __future__ import annotations

import hashlib


class Trace:
    def __init__(self, keep: bool = False) -> None:
        self._hash = hashlib.sha256()
        self.events = 0
        self.lines: list[str] | None = [] if keep else None

    def _add(self, line: str) -> int:
        self._hash.update(line.encode())
        self._hash.update(b"\n")
        self.events += 1
        if self.lines is not None:
            self.lines.append(line)
        return self.events

    def message(self, t: float, sender: str, receiver: str, key: str, payload: bytes) -> int:
        return self._add(f"{t!r} msg {sender} {receiver} {key} {hashlib.sha256(payload).hexdigest()}")

    def liveliness(self, t: float, observer: str, node: str, alive: bool) -> int:
        return self._add(f"{t!r} sight {observer} {node} {'up' if alive else 'down'}")

    def note(self, t: float, what: str) -> int:
        """A fault applied, a process started or stopped, an operator's command."""
        return self._add(f"{t!r} {what}")

    @property
    def sha256(self) -> str:
        return self._hash.hexdigest()
