"""Sequence numbers: each stage runs every input once, in order; each sink counts outputs once.

A chain's source numbers its frames 0, 1, 2, ... within a *run* (one activation of the chain).
A stage instance keeps the next sequence number it must run: earlier ones are duplicates
(dropped), later ones wait in a reorder buffer. Migration ships that number with the state, so
the new host resumes exactly where the old one stopped, whatever order the inputs reach it in.

Both report what they have consumed (`Consumed`): the acknowledgement the producers' custody
buffers (`autopower.node.custody`) act on, so a frame lost on a silently cut link is resent.
"""

from __future__ import annotations

import bisect
import math
import statistics
import struct
import zlib
from collections import deque
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from autopower.protocol import Consumed
from autopower.protocol.messages import MAX_MISSING_RANGES

T = TypeVar("T")

MAX_MISSING = MAX_MISSING_RANGES  # missing ranges listed in one report (the lowest ones)
GATE_MAX_GAP_S = 10.0  # wall seconds a gap may stay open (several resend rounds) before it is given up
GATE_MAX_PENDING = 512  # inputs waiting behind a gap, at most (memory: camera frames are 230 kB)
# Outputs a sink keeps above a gap before it gives the gap up. A gap its producer gave up on (a
# stage's gate skipped those inputs) never fills; without this bound everything after it would stay
# in the ledger, and its report and journal would grow with the mission until the sink fell behind.
# 4,096 outputs are 18 s of both camera chains at x55, far beyond custody's resends.
SINK_MAX_AHEAD = 4096
OLDER_RUNS_KEPT = 4  # a sink remembers what it got of this many runs before its current one


def missing_between(low: int, high: int, have) -> tuple[tuple[int, int], ...]:
    """The seqs in [low, high] not in ``have``, as inclusive (first, last) ranges, lowest first, at
    most MAX_MISSING of them (`Consumed.missing`). Walks what is there, not the whole span."""
    out = []
    start = low
    for seq in sorted(s for s in have if low <= s <= high):
        if seq > start:
            out.append((start, seq - 1))
            if len(out) == MAX_MISSING:
                return tuple(out)
        start = seq + 1
    if start <= high and len(out) < MAX_MISSING:
        out.append((start, high))
    return tuple(out)


def ranges_of(seqs) -> tuple[tuple[int, int], ...]:
    """Sorted, distinct seqs as inclusive (first, last) ranges."""
    out: list[list[int]] = []
    for seq in seqs:
        if out and seq == out[-1][1] + 1:
            out[-1][1] = seq
        else:
            out.append([seq, seq])
    return tuple((a, b) for a, b in out)


def in_ranges(ranges: tuple[tuple[int, int], ...], seq: int) -> bool:
    """Is ``seq`` in one of the sorted, disjoint ``ranges``?"""
    i = bisect.bisect_right(ranges, (seq, math.inf)) - 1
    return i >= 0 and ranges[i][0] <= seq <= ranges[i][1]


@dataclass
class SequenceGate(Generic[T]):
    """In-order, exactly-once admission of numbered items."""

    next_seq: int | None = None  # None: start at the first item offered
    pending: dict[int, T] = field(default_factory=dict)
    duplicates: int = 0
    redundant: int = 0  # second copies where a resend was involved (expected, dropped)
    skipped: int = 0  # seqs given up as lost (a gap that stayed open too long)
    consumed_elsewhere: int = 0  # seqs skipped because their producer says another instance had them
    max_pending: int = GATE_MAX_PENDING
    max_gap_s: float = GATE_MAX_GAP_S
    _gap_since: float | None = None  # since when the oldest open gap has been the oldest (wall seconds)
    catch_up_below: int | None = None  # started without state below its first input: these are recomputed
    # the highest floor its producers' fresh frames have carried (`ChainFrame.floor`), and when the
    # last one came: a gap at or above it is still held by a live producer, which resends it
    producer_floor: int | None = None
    _floor_heard: float | None = None
    resent: deque = field(default_factory=lambda: deque(maxlen=4096))  # recent seqs first offered as a resend
    released: int = 0  # inputs handed on to run (its instance's component has seen them)

    def offer(self, seq: int, item: T, floor: int | None = None, resent: bool = False,
              now: float | None = None) -> list[T]:
        """Items now ready to run, in sequence order (possibly none).

        ``floor`` is the producer's lowest unacknowledged seq (see `ChainFrame.floor`): a gate
        with no position starts there, and one waiting below it stops waiting. A second copy is
        *redundant* when a resend is involved (``resent``, now or the first time: the original
        was only late), as at the sink (`SinkLedger.record`); otherwise it is a *duplicate*.
        """
        early: list[T] = []
        if floor is not None and not resent:  # a resent copy carries the floor of its first sending
            self.producer_floor = floor if self.producer_floor is None else max(floor, self.producer_floor)
            self._floor_heard = now
        if self.next_seq is None:
            self.next_seq = seq if floor is None else min(seq, floor)
            if self.next_seq < seq:
                self.catch_up_below = seq
        elif floor is not None and floor > self.next_seq:
            # everything below the floor was acknowledged by some instance of this stage: what is
            # not waiting here will not come (a previous instance ran it). What waits here runs,
            # in order, past those gaps: it is acknowledged by this gate, and a seq another
            # instance consumed never comes here, so waiting for it would hold everything behind
            # it until a crash lost it
            early = self._release_below(floor)
        if seq < self.next_seq or seq in self.pending:
            if resent or seq in self.resent:
                self.redundant += 1
            else:
                self.duplicates += 1
            return early
        if resent:
            self.resent.append(seq)
        self.pending[seq] = item
        ready = early + self.drain()
        if not self.pending:
            self._gap_since = None
            return ready
        if self._gap_since is None or ready:
            # a gap is timed from when it became the oldest: inputs released here filled the one
            # that was, so what still waits is behind a younger gap, whose resend may be on its way
            self._gap_since = now
        open_s = now - self._gap_since if now is not None and self._gap_since is not None else 0.0
        if len(self.pending) > self.max_pending or (open_s > self.max_gap_s and not self.held_upstream(now)):
            # The producers resend what is missing (custody), and a migration can hold inputs up
            # for seconds; a gap still open after this long that no live producer says it holds
            # is lost for good (its producer died or gave it up): stalling the stage forever
            # would lose everything after it too. One a producer holds waits for its resend.
            self._gap_since = None
            first = min(self.pending)
            self.skipped += first - self.next_seq
            self.next_seq = first
            ready += self.drain()
        return ready

    def held_upstream(self, now: float | None) -> bool:
        """Did a producer say, within the gate's limit, that it still holds the oldest gap (its floor
        at or below it)? Then it is resending it (custody keeps a frame for minutes and many resends),
        and giving the gap up would lose an input a lossy link is only slow to carry."""
        if self.producer_floor is None or self.next_seq is None or self.producer_floor > self.next_seq:
            return False
        return now is None or self._floor_heard is None or now - self._floor_heard <= self.max_gap_s

    def skips_below(self, floor: int | None) -> bool:
        """Would ``floor`` move this gate past a seq that is not waiting here (`_release_below`)?"""
        if floor is None or self.next_seq is None or floor <= self.next_seq:
            return False
        return sum(1 for seq in self.pending if seq < floor) < floor - self.next_seq

    def _release_below(self, floor: int) -> list[T]:
        """Move to ``floor``, counting the seqs below it that are not here as consumed elsewhere and
        releasing, in order, those that are."""
        released = []
        for seq in sorted(s for s in self.pending if s < floor):
            self.consumed_elsewhere += seq - self.next_seq
            released.append(self.pending.pop(seq))
            self.next_seq = seq + 1
        self.released += len(released)
        self.consumed_elsewhere += floor - self.next_seq
        self.next_seq = floor
        if not self.pending:
            self._gap_since = None
        return released

    def report(self, run: int, generation: int) -> Consumed | None:
        """What this gate has consumed (None before its first input: it starts wherever that is)."""
        if self.next_seq is None:
            return None
        top = max(self.pending, default=self.next_seq - 1)
        return Consumed(run=run, generation=generation, next_seq=self.next_seq, max_seq=top,
                        missing=missing_between(self.next_seq, top, self.pending))

    def drain(self) -> list[T]:
        ready = []
        while self.next_seq is not None and self.next_seq in self.pending:
            ready.append(self.pending.pop(self.next_seq))
            self.next_seq += 1
        self.released += len(ready)
        return ready

    def recent_resends(self, window: int = 512) -> tuple[int, ...]:
        """Seqs that first came as resends, near where the gate is (what a migration carries along)."""
        low = (self.next_seq or 0) - window
        return tuple(s for s in self.resent if s >= low)

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
    return fold_crc(digest, seq, zlib.crc32(data))


def fold_crc(digest: int, seq: int, data_crc: int) -> int:
    """`fold_digest` from the CRC-32 of the output (what a sink keeps of outputs not yet in order)."""
    return zlib.crc32(struct.pack("<QI", seq, data_crc), digest)


@dataclass
class SinkLedger:
    """Counts one chain's outputs at its sink: received, duplicated, contiguous prefix."""

    run: int = -1
    contiguous: int = 0  # every seq < contiguous has arrived (or was given up: see SINK_MAX_AHEAD)
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
    _waiting: dict[int, int] = field(default_factory=dict)  # CRC-32 of the data of seqs above the prefix
    redundant_total: int = 0  # second copies where a retransmission was involved (expected)
    _resent: deque = field(default_factory=lambda: deque(maxlen=4096))  # recent seqs first received as a resend
    given_up_total: int = 0  # seqs whose gap stayed open behind SINK_MAX_AHEAD outputs (lost, unless they come late)
    late_total: int = 0  # given-up seqs that came after all (delivered, counted as received)
    _given_up: deque = field(default_factory=lambda: deque(maxlen=SINK_MAX_AHEAD))  # recent given-up seqs
    # run -> (its contiguous prefix, the seqs above it) for the runs before this one: an older run's
    # output that comes after its chain started over is handed on once, never twice
    older: dict[int, tuple[int, set[int]]] = field(default_factory=dict)

    def record(self, run: int, seq: int, latency_ms: float | None = None, data: bytes = b"",
               attempt: int = 0, crc: int | None = None) -> bool:
        """True if this output is new (``crc``: the CRC-32 of ``data``, when only that is known).

        A second copy is *redundant* when a retransmission is involved (either copy is one: the
        first was only late); otherwise it is a *duplicate*, which means an output was produced
        twice, and must never happen.
        """
        if run < self.run:
            return self._record_older(run, seq, attempt)
        if run > self.run:
            if self.run >= 0:
                self.older[self.run] = (self.contiguous, self.above)
                for gone in sorted(self.older)[:-OLDER_RUNS_KEPT]:
                    del self.older[gone]
            self.run, self.contiguous, self.above = run, 0, set()
            self.received, self.duplicates, self.max_seq = 0, 0, -1
            self.latency_ms_max = 0.0
            self.latencies_ms.clear()
            self.digest, self._waiting = 0, {}
            self._resent.clear()
            self._given_up.clear()
        if seq < self.contiguous and seq in self._given_up:  # late, not lost after all
            self._given_up.remove(seq)
            self.late_total += 1
            self.received += 1
            self.received_total += 1
            return True
        if seq < self.contiguous or seq in self.above:
            if attempt > 0 or seq in self._resent:
                self.redundant_total += 1
            else:
                self.duplicates += 1
                self.duplicates_total += 1
            return False
        if attempt > 0:
            self._resent.append(seq)
        self.above.add(seq)
        self._waiting[seq] = zlib.crc32(data) if crc is None else crc
        self._advance()
        if len(self.above) > SINK_MAX_AHEAD:  # the gap below them will not fill: give it up
            first = min(self.above)
            self._given_up.extend(range(max(self.contiguous, first - SINK_MAX_AHEAD), first))
            self.given_up_total += first - self.contiguous
            self.contiguous = first  # the digest covers what arrived; a given-up seq is not in it
            self._advance()
        self.received += 1
        self.received_total += 1
        self.max_seq = max(self.max_seq, seq)
        if latency_ms is not None:
            self.latencies_ms.append(latency_ms)
            self.latency_ms_max = max(self.latency_ms_max, latency_ms)
        return True

    def _record_older(self, run: int, seq: int, attempt: int) -> bool:
        """An output of a run before this one (it came after its chain started over): False always
        (it is not this run's), counted *stale* the first time (the caller hands it on) and as a
        second copy after that (redundant with a resend involved, else a duplicate: not handed on)."""
        kept = self.older.get(run)
        if kept is None and (len(self.older) < OLDER_RUNS_KEPT or run > min(self.older)):
            # a run this sink never saw an output of (all held upstream when its chain started
            # over): remembered from now on, so that its results are reported (`older_reports`:
            # their producers let them go) and a second copy is told from the first
            kept = (0, set())
            self.older[run] = kept
            for gone in sorted(self.older)[:-OLDER_RUNS_KEPT]:
                del self.older[gone]
        if kept is None:  # older than the runs kept: handed on as stale, unchecked
            self.stale += 1
            return False
        contiguous, above = kept
        if seq < contiguous or seq in above:
            if attempt > 0:
                self.redundant_total += 1
            else:
                self.duplicates_total += 1
            return False
        above.add(seq)
        while contiguous in above:
            above.remove(contiguous)
            contiguous += 1
        self.older[run] = (contiguous, above)
        self.stale += 1
        return False

    def _advance(self) -> None:
        while self.contiguous in self.above:
            self.above.remove(self.contiguous)
            self.digest = fold_crc(self.digest, self.contiguous, self._waiting.pop(self.contiguous))
            self.contiguous += 1

    def report(self) -> Consumed | None:
        """What this sink has received (None before its first output)."""
        if self.run < 0:
            return None
        return Consumed(run=self.run, generation=0, next_seq=self.contiguous, max_seq=self.max_seq,
                        missing=missing_between(self.contiguous, self.max_seq, self.above))

    def older_reports(self) -> tuple[Consumed, ...]:
        """What this sink got of each run before its current one that it remembers, oldest first:
        their results still to come are handed on once (`_record_older`), so they are not obsolete."""
        out = []
        for run, (contiguous, above) in sorted(self.older.items()):
            top = max(above, default=contiguous - 1)
            out.append(Consumed(run=run, generation=0, next_seq=contiguous, max_seq=top,
                                missing=missing_between(contiguous, top, above)))
        return tuple(out)

    def state(self) -> dict:
        """What a restarted sink needs to go on exactly where this one is (`from_state`): JSON-able."""
        return {"run": self.run, "contiguous": self.contiguous, "above": sorted(self.above),
                "waiting": {str(s): c for s, c in self._waiting.items()}, "received": self.received,
                "max_seq": self.max_seq, "received_total": self.received_total,
                "duplicates_total": self.duplicates_total, "redundant_total": self.redundant_total,
                "digest": self.digest, "given_up_total": self.given_up_total, "late_total": self.late_total,
                "older": {str(r): [c, sorted(a)] for r, (c, a) in self.older.items()}}

    @classmethod
    def from_state(cls, state: dict) -> "SinkLedger":
        """A ledger that goes on from `state` (ValueError/KeyError/TypeError if it is not one)."""
        ledger = cls(run=int(state["run"]), contiguous=int(state["contiguous"]),
                     above={int(s) for s in state["above"]}, received=int(state["received"]),
                     max_seq=int(state["max_seq"]), received_total=int(state["received_total"]),
                     duplicates_total=int(state["duplicates_total"]),
                     redundant_total=int(state["redundant_total"]), digest=int(state["digest"]))
        ledger._waiting = {int(s): int(c) for s, c in state["waiting"].items()}
        ledger.given_up_total, ledger.late_total = int(state.get("given_up_total", 0)), int(state.get("late_total", 0))
        ledger.older = {int(r): (int(c), {int(s) for s in a}) for r, (c, a) in state.get("older", {}).items()}
        if any(r >= ledger.run for r in ledger.older):
            raise ValueError("a sink state that remembers a run not older than its own")
        if set(ledger._waiting) != ledger.above or any(s < ledger.contiguous for s in ledger.above):
            raise ValueError("a sink state whose outputs above the prefix do not add up")
        return ledger

    @property
    def gaps(self) -> int:
        """Seqs below the highest seen that have not arrived (yet)."""
        return self.max_seq + 1 - self.received

    @property
    def latency_ms_p50(self) -> float:
        return statistics.median(self.latencies_ms) if self.latencies_ms else 0.0
