"""Sequence numbers: each stage runs every input once, in order; each sink counts outputs once.

A chain's source numbers its frames 0, 1, 2, ... within a *run* (one activation of the chain).
A stage instance keeps the next sequence number it must run: earlier ones are duplicates
(dropped), later ones wait in a reorder buffer. Migration ships that number with the state, so
the new host resumes exactly where the old one stopped, whatever order the inputs reach it in.
"""

from __future__ import annotations

import statistics
import struct
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass
class SequenceGate(Generic[T]):
    """In-order, exactly-once admission of numbered items."""

    next_seq: int | None = None  # None: start at the first item offered
    pending: dict[int, T] = field(default_factory=dict)
    duplicates: int = 0

    def offer(self, seq: int, item: T) -> list[T]:
        """Items now ready to run, in sequence order (possibly none)."""
        if self.next_seq is None:
            self.next_seq = seq
        if seq < self.next_seq or seq in self.pending:
            self.duplicates += 1
            return []
        self.pending[seq] = item
        return self.drain()

    def drain(self) -> list[T]:
        ready = []
        while self.next_seq is not None and self.next_seq in self.pending:
            ready.append(self.pending.pop(self.next_seq))
            self.next_seq += 1
        return ready

    def take_pending(self) -> list[T]:
        """Everything waiting, in order (for a migration), leaving the gate empty."""
        items = [self.pending[s] for s in sorted(self.pending)]
        self.pending.clear()
        return items


def fold_digest(digest: int, seq: int, data: bytes) -> int:
    """Extend an in-order digest of a chain's outputs by output ``seq``.

    Two sinks (or a sink and an offline re-run of the chain) that saw the same outputs for seqs
    0..n-1 have the same digest: a cheap end-to-end check that nothing was lost, repeated,
    reordered or computed from the wrong state.
    """
    return zlib.crc32(struct.pack("<QI", seq, zlib.crc32(data)), digest)


@dataclass
class SinkLedger:
    """Counts one chain's outputs at its sink: received, duplicated, contiguous prefix."""

    run: int = -1
    contiguous: int = 0  # every seq < contiguous has arrived
    above: set[int] = field(default_factory=set)  # arrived seqs >= contiguous
    received: int = 0
    duplicates: int = 0
    max_seq: int = -1
    stale: int = 0
    received_total: int = 0
    duplicates_total: int = 0
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=512))
    latency_ms_max: float = 0.0
    digest: int = 0  # fold_digest over the outputs of seqs < contiguous
    _waiting: dict[int, bytes] = field(default_factory=dict)  # data of seqs above the prefix

    def record(self, run: int, seq: int, latency_ms: float | None = None, data: bytes = b"") -> bool:
        """True if this output is new."""
        if run < self.run:
            self.stale += 1
            return False
        if run > self.run:
            self.run, self.contiguous, self.above = run, 0, set()
            self.received, self.duplicates, self.max_seq = 0, 0, -1
            self.latency_ms_max = 0.0
            self.latencies_ms.clear()
            self.digest, self._waiting = 0, {}
        if seq < self.contiguous or seq in self.above:
            self.duplicates += 1
            self.duplicates_total += 1
            return False
        self.above.add(seq)
        self._waiting[seq] = data
        while self.contiguous in self.above:
            self.above.remove(self.contiguous)
            self.digest = fold_digest(self.digest, self.contiguous, self._waiting.pop(self.contiguous))
            self.contiguous += 1
        self.received += 1
        self.received_total += 1
        self.max_seq = max(self.max_seq, seq)
        if latency_ms is not None:
            self.latencies_ms.append(latency_ms)
            self.latency_ms_max = max(self.latency_ms_max, latency_ms)
        return True

    @property
    def gaps(self) -> int:
        """Seqs below the highest seen that have not arrived (yet)."""
        return self.max_seq + 1 - self.received

    @property
    def latency_ms_p50(self) -> float:
        return statistics.median(self.latencies_ms) if self.latencies_ms else 0.0
