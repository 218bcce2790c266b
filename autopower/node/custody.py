"""Custody of sent frames: kept until their consumer reports them consumed, resent if lost.

Zenoh delivers reliably *within* a session, but a link cut silently loses whatever is in
flight on it until the lease expires (about 0.5 s), and nothing retransmits across sessions.
So every producer (a chain's source, and every stage for its outputs) keeps each frame it
emits in custody, keyed by (chain, target, run, seq), until the frame's consumer (the next
stage's host, or the chain's sink) acknowledges it.

The acknowledgement is the `Consumed` report every node sends with its status, in one `Ack` to
each node that feeds it (per hop: run, the in-order prefix it has consumed, the highest seq seen and the seqs missing
below it). A stage's input leaves custody once it is in that prefix, run; one that waits in the
gate behind a gap stays (an instance may move on and what waited in it never land), and is not
resent while the instance that has it reports it. A chain's result leaves once its sink reports
it received: delivered. A frame is resent when a report made at least ``resend_after_s`` after the frame
was last sent still lacks it: the report, not a timer, decides, so a frame that is only
slow (queued behind a migration) is not resent while its consumer keeps receiving. Consumers
drop second copies (the stage's sequence gate, the sink's ledger), so resending is safe.

A frame sent once and past the highest seq its consumer has seen is either lost with everything
sent after it, or still on its way behind the others. While that highest seq keeps rising (the
consumer got a later frame than before within ``resend_after_s`` of its report) the link
delivers, only slower than the frames are sent (a radio slowed below the chain's rate): a copy
would queue behind its original and double what the slow link must carry, so it waits. It is
resent once the consumer has received nothing new for ``resend_after_s``; one lost while later
ones arrive is reported missing below the highest seq, and resent as before. A frame already
resent never waits so: its loss is known (a cut), and when the link comes back the copies of the
others arriving raise the highest seq too, which says nothing about where this one is.

A report speaks only for what reached its consumer's loop: frames still waiting in the
consumer's event queue are in none of its counts. The status says how long the oldest of them
had waited (`NodeStatus.queue_wait_s`), and that much is taken off the report's time before it
may call a frame lost. Without it a consumer more than ``resend_after_s`` behind was sent again
its whole queue, which it decoded only to drop: at x55 on a loaded machine each camera robot
resent half as many frames as it produced (1.2 per frame in the worst seconds), and the base
station, already short of CPU, fell further behind (a resend storm that lasted until the load
dropped). A frame is only resent later, never held back for good:
once the queue is taken in, a report that still lacks it calls it lost.

Responsibility moves downstream hop by hop: once a stage has consumed an input, its output is
that stage's host's to keep, so a frame lost after a stateful stage (MCL) is resent from that
stage's output, never recomputed (which would run MCL twice on one input).

Custody is bounded (frames per hop, bytes per node, age); what is evicted can no longer be
resent and is counted, so a loss is visible instead of silent. A source does not fill it up to
that point when its consumer is behind: while its first hop is full (its frames per hop, or its
share of the bytes) and the oldest frame in it waits for longer than a resend would, it skips its
captures, counted as missed periods (``missed-periods-backlog``), so a consumer that falls behind
gets the stream late but whole, never with holes (`has_room`). What it holds then goes to the
consumer's next instance, which says it has nothing before its first input
(`Acknowledging.consumed`): waiting for a first input that the backed-up source will not capture
would stall the chain for good.

A chain's results (the frames for its sink) are the exception: they are what the operator wants,
so they are kept, and resent, for as long as their sink needs to come back (store and forward),
bounded only by the node's hold budget (scenario ``[delivery] hold_budget_mb``). Beyond it the
oldest results are dropped, and returned to the caller to be counted as dropped by the budget,
apart from losses.
"""

from __future__ import annotations

import heapq
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Mapping

from autopower.node.sequencing import MAX_MISSING, OLDER_RUNS_KEPT, in_ranges
from autopower.protocol import ChainFrame, Consumed

RESEND_AFTER_S = 1.0  # wall seconds between a send and a report that may call the frame lost
MAX_FRAMES_PER_HOP = 1024
MAX_BYTES = 64 * 1024 * 1024  # camera frames are 230 kB: ~280 of them
MAX_AGE_S = 300.0  # a frame nobody acknowledged for this long is given up
MAX_ATTEMPTS = 20
HOLD_BUDGET_BYTES = 64 * 2**20  # the scenario's default `[delivery] hold_budget_mb`


@dataclass
class Held:
    frame: ChainFrame
    kept_unix: float
    sent_unix: float | None  # None: not on the wire yet (no route to its consumer)
    result: bool = False  # a chain's result for its sink: bounded by the hold budget alone
    # False only while no copy has left this node: its first send found no route (`held_back`).
    # Its first copy to go is then the chain's own traffic, not a resend (`resend`).
    on_air: bool = True


@dataclass(frozen=True)
class Report:
    """A consumer's `Consumed`, with who made it and when."""

    node: str
    t_unix: float
    consumed: Consumed
    queue_wait_s: float = 0.0  # what waited in the consumer's event queue this long is not in ``consumed``
    # a sink's: run -> what it got of that run before its current one (`Ack.older`)
    older: Mapping[int, Consumed] = field(default_factory=dict)

    def result_taken(self, run: int, seq: int) -> bool:
        """Has the sink taken this result in, or can it no more? A result of an older run than the
        sink's is obsolete only once the sink has forgotten that run (`SinkLedger.older`: it keeps
        OLDER_RUNS_KEPT, and reports them all): until then it hands such a result on once (a chain
        that started over leaves its old run's tail held upstream: a cut sink, a frozen base
        station), so the result is kept and sent."""
        said = self.for_run(run)
        return True if said is None else is_consumed(said, run, seq)

    def for_run(self, run: int) -> Consumed | None:
        """What the sink said of ``run``: its current run's report, an older run's it remembers, or
        that it has none of a run it may still take (nothing received yet); None for a run it has
        forgotten, or one newer than its own (not reported yet: `is_consumed` keeps its frames)."""
        if run >= self.consumed.run:
            return self.consumed
        if run in self.older:
            return self.older[run]
        if len(self.older) >= OLDER_RUNS_KEPT and run < min(self.older):
            return None
        return Consumed(run=run, generation=0, next_seq=0, max_seq=-1, missing=())


Hop = tuple[str, int]  # (chain, target)


def hop_key(chain: str, target: int) -> str:
    """The key of a hop in `NodeStatus.consumed`."""
    return f"{chain}#{target}"


def parse_hop_key(key: str) -> Hop | None:
    chain, sep, target = key.rpartition("#")
    if not sep or not chain or not target.isdigit():
        return None
    return chain, int(target)


def is_consumed(report: Consumed, run: int, seq: int) -> bool:
    """Has the consumer taken this frame in (or moved past its run, making it obsolete)?"""
    if run < report.run:
        return True
    if run > report.run:
        return False
    if seq < report.next_seq:
        return True
    if seq > report.max_seq:
        return False
    if in_ranges(report.missing, seq):
        return False
    # Beyond a truncated missing list nothing is known: counting such a frame as received would drop
    # it from custody unsent. It stays held, and is not resent either (`beyond_known`) until a later
    # report lists it or moves past it.
    return not beyond_known(report, seq)


def is_run(report: Consumed, run: int, seq: int) -> bool:
    """Has the consumer run this frame (or moved past its run)? Only this frees a stage's input.

    A stage's gate also reports the inputs waiting behind a gap as received (`is_consumed`), but
    waiting is not running: the instance may migrate and its state, with what waited, never land.
    Its producer keeps them until the stage has run them, so the stage's next instance, which
    reports them missing, gets them again instead of a gap no one can fill."""
    return run < report.run or (run == report.run and seq < report.next_seq)


def beyond_known(report: Consumed, seq: int) -> bool:
    """``seq`` is past the last range a truncated missing list names: neither confirmed nor reported lost."""
    return len(report.missing) >= MAX_MISSING and report.missing[-1][1] < seq <= report.max_seq


class Custody:
    def __init__(self, *, resend_after_s: float = RESEND_AFTER_S, max_frames_per_hop: int = MAX_FRAMES_PER_HOP,
                 max_bytes: int = MAX_BYTES, max_age_s: float = MAX_AGE_S, max_attempts: int = MAX_ATTEMPTS,
                 hold_budget_bytes: int = HOLD_BUDGET_BYTES):
        self.resend_after_s = resend_after_s
        self.hold_budget_bytes = hold_budget_bytes
        self.max_frames_per_hop = max_frames_per_hop
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self.max_attempts = max_attempts
        self.hops: dict[Hop, OrderedDict[tuple[int, int], Held]] = {}
        self.reports: dict[Hop, Report] = {}
        # hop -> the time of the consumer's last report whose highest seq rose above the one in its
        # report before (the same instance and run): frames past that seq wait while it keeps rising
        # (see the module's rules)
        self._advanced: dict[Hop, float] = {}
        self.bytes = 0
        self.hop_bytes: dict[Hop, int] = {}  # of ``bytes``, each hop's
        self.kept = 0
        self.acknowledged = 0
        self.resent = 0
        self.evicted = 0  # dropped unacknowledged (bounds, age, attempts): possibly lost
        # of ``evicted``, why: the custody full (frames per hop, bytes), or given up (age, attempts)
        self.evicted_full = 0
        self.evicted_given_up = 0
        self.result_bytes = 0  # of ``bytes``: the results kept (what the hold budget bounds)
        self.dropped_by_budget = 0  # results dropped, the budget full (returned by `keep`, counted here)
        self.dropped_by_budget_bytes = 0
        # (hop, run) -> a min-heap of the seqs kept, those dropped since left in until they come
        # to the top: the floor is asked for every frame sent. (A scan of the hop each time its
        # lowest frame was acknowledged cost a camera robot 2 % of a core at x55, where a late
        # consumer leaves a hop holding thousands of frames.)
        self._seqs: dict[tuple[Hop, int], list[int]] = {}

    def __len__(self) -> int:
        return sum(len(h) for h in self.hops.values())

    def chains(self) -> set[str]:
        """The chains of the frames held (whose acknowledgements this node needs)."""
        return {chain for (chain, _), frames in self.hops.items() if frames}

    # ---- producing --------------------------------------------------------------------------------
    def keep(self, frame: ChainFrame, now: float, sent: bool = True, result: bool = False) -> list[ChainFrame]:
        """Hold ``frame`` until its consumer acknowledges it; the results this drops, the hold budget
        full (oldest first: the caller counts them as dropped by the budget, never as lost).

        ``result``: the frame is a chain's result for its sink (see the module's rules)."""
        hop_id = (frame.chain, frame.target)
        hop = self.hops.setdefault(hop_id, OrderedDict())
        key = (frame.run, frame.seq)
        if key in hop:
            return []
        hop[key] = Held(frame=frame, kept_unix=now, sent_unix=now if sent else None, result=result)
        seqs = self._seqs.setdefault((hop_id, frame.run), [])
        heapq.heappush(seqs, frame.seq)
        if len(seqs) > 2 * len(hop) + 64:  # mostly seqs dropped below a lasting floor: start afresh
            seqs[:] = sorted(seq for (run, seq) in hop if run == frame.run)  # a sorted list is a heap
        self.bytes += len(frame.payload)
        self.hop_bytes[hop_id] = self.hop_bytes.get(hop_id, 0) + len(frame.payload)
        self.kept += 1
        if result:
            self.result_bytes += len(frame.payload)
            return self._over_budget()
        while len(hop) > self.max_frames_per_hop:
            self._drop(hop, next(iter(hop)), evicted=True)
            self.evicted_full += 1
        while self.bytes - self.result_bytes > self.max_bytes:
            oldest = min((h for h in self.hops.values() if h and not next(iter(h.values())).result),
                         key=lambda h: next(iter(h.values())).kept_unix)
            self._drop(oldest, next(iter(oldest)), evicted=True)
            self.evicted_full += 1
        return []

    def has_room(self, chain: str, target: int, size: int, now: float, sharers: int = 1) -> bool:
        """Whether a source may capture a frame of ``size`` bytes for this hop: False only while the
        hop is full (its frames, or its share of the bytes: 1 / ``sharers``, the node's sources)
        *and* its consumer is behind (the oldest frame held was kept ``resend_after_s`` ago or more).

        A consumer that has fallen this far behind (a stage stalled by a migration, a machine
        that cannot keep up) is not sent more. Evicting the oldest frame instead opened a gap in
        the middle of the stream that its gate waited on and then gave up: the frames held were
        lost, and the newest kept coming. The share keeps one stalled camera chain from stopping a
        healthy chain's source beside it. A hop that is full only because its acknowledgements
        take a status period to come back (a camera hop at x100 fills in a third of a second) is
        not behind: it keeps the newest frame and `keep` evicts the oldest, most likely run by now."""
        hop = self.hops.get((chain, target))
        if not hop:
            return True
        share = self.max_bytes // max(1, sharers)
        full = (len(hop) >= self.max_frames_per_hop or self.hop_bytes.get((chain, target), 0) + size > share
                or self.bytes - self.result_bytes + size > self.max_bytes)
        return not full or now - next(iter(hop.values())).kept_unix < self.resend_after_s

    def held_for(self, chain: str, target: int) -> int:
        """How many frames this node holds for a hop."""
        return len(self.hops.get((chain, target), ()))

    def _over_budget(self) -> list[ChainFrame]:
        """Drop the oldest results while they take more than the hold budget."""
        dropped = []
        while self.result_bytes > self.hold_budget_bytes:
            oldest = min((h for h in self.hops.values() if h and next(iter(h.values())).result),
                         key=lambda h: next(iter(h.values())).kept_unix)
            held = oldest[next(iter(oldest))]
            self._drop(oldest, next(iter(oldest)), evicted=None)
            self.dropped_by_budget += 1
            self.dropped_by_budget_bytes += len(held.frame.payload)
            dropped.append(held.frame)
        return dropped

    def floor(self, chain: str, target: int, run: int, default: int) -> int:
        """The lowest seq of a hop and run still held unacknowledged (``default`` if none is)."""
        seqs = self._seqs.get(((chain, target), run))
        if not seqs:
            return default
        hop = self.hops.get((chain, target), {})
        while seqs and (run, seqs[0]) not in hop:
            heapq.heappop(seqs)
        if not seqs:
            del self._seqs[((chain, target), run)]
            return default
        return seqs[0]

    def mark(self, frame: ChainFrame, sent_unix: float | None) -> None:
        """The frame went on the wire now (or was held back: None)."""
        held = self.hops.get((frame.chain, frame.target), {}).get((frame.run, frame.seq))
        if held is not None:
            held.sent_unix = sent_unix
            if sent_unix is not None:  # a copy has left (a held result its sink routes again): a
                held.on_air = True  # copy after it is a resend, which a sink that has the first drops

    def forget(self, frame: ChainFrame) -> None:
        """Stop holding a frame its producer dropped itself (a result a full hold let go, counted
        there): left here it was never resendable (`mark(..., None)`) and kept the hop's floor low."""
        hop = self.hops.get((frame.chain, frame.target))
        if hop is not None and (frame.run, frame.seq) in hop:
            self._drop(hop, (frame.run, frame.seq), evicted=None)

    def _drop(self, hop: OrderedDict, key: tuple[int, int], evicted: bool | None) -> None:
        """``evicted``: True given up (counted), False acknowledged (counted), None forgotten."""
        held = hop.pop(key)
        if not hop:  # the hop's heaps hold only dropped seqs
            for run in [r for (h, r) in self._seqs if h == (held.frame.chain, held.frame.target)]:
                del self._seqs[((held.frame.chain, held.frame.target), run)]
        self.bytes -= len(held.frame.payload)
        held_hop = (held.frame.chain, held.frame.target)
        self.hop_bytes[held_hop] = self.hop_bytes.get(held_hop, 0) - len(held.frame.payload)
        if not hop:
            self.hop_bytes.pop(held_hop, None)
        if held.result:
            self.result_bytes -= len(held.frame.payload)
        if evicted:
            self.evicted += 1
        elif evicted is not None:
            self.acknowledged += 1

    def forget_chain(self, chain: str, keep_target: int | None = None) -> None:
        """The chain stopped: the frames for its stages have no consumer any more (not a loss).

        ``keep_target``: the hop of its results (to its sink), kept: its sink still takes them. A
        chain is stopped when the base station loses its source robot for a moment, and adopted
        again in the same run when the robot is back; dropping its results from custody as well
        would count them as acknowledged, and those lost in flight would never come.
        """
        for (name, target), hop in list(self.hops.items()):
            if name == chain and target != keep_target:
                for key in list(hop):
                    self._drop(hop, key, evicted=False)

    # ---- acknowledgements --------------------------------------------------------------------------
    def on_report(self, chain: str, target: int, report: Report) -> None:
        """Remember the newest report for a hop (a newer stage generation, or the same one later)."""
        hop = (chain, target)
        known = self.reports.get(hop)
        c = report.consumed
        if known is not None:
            k = known.consumed
            if (c.generation, c.run) < (k.generation, k.run):
                return
            if (c.generation, c.run) == (k.generation, k.run) and report.t_unix <= known.t_unix:
                return
        if known is not None and (c.generation, c.run) == (known.consumed.generation, known.consumed.run) \
                and c.max_seq > known.consumed.max_seq:
            self._advanced[hop] = report.t_unix
        elif known is None or (c.generation, c.run) != (known.consumed.generation, known.consumed.run):
            self._advanced.pop(hop, None)  # a new instance or run: nothing seen rise yet
        self.reports[hop] = report
        frames = self.hops.get(hop)
        if frames:
            # a sink's report speaks for what it delivered; a stage's only for what it ran (`is_run`)
            done = [k for k, held in frames.items()
                    if (report.result_taken(held.frame.run, held.frame.seq) if held.result
                        else is_run(c, held.frame.run, held.frame.seq))]
            for key in done:
                self._drop(frames, key, evicted=False)

    def due(self, now: float) -> list[tuple[str, Held]]:
        """Frames to resend now, each with the node that lacks it (the consumer that reported).

        Also gives up frames that are too old or were resent too often. Nothing changes for
        the returned frames until the caller `resend`s them (a frame with no route yet stays
        due and is tried again).
        """
        out = []
        for hop, frames in self.hops.items():
            report = self.reports.get(hop)
            for key in list(frames):
                held = frames[key]
                if not held.result and (now - held.kept_unix > self.max_age_s
                                        or held.frame.attempt >= self.max_attempts):
                    self._drop(frames, key, evicted=True)
                    self.evicted_given_up += 1
                    continue
                said = (None if report is None
                        else report.consumed if held.frame.run == report.consumed.run
                        else report.for_run(held.frame.run) if held.result and held.frame.run < report.consumed.run
                        else None)  # a newer run's frames wait for the consumer's first word of it
                if (said is None or held.sent_unix is None
                        or report.t_unix - report.queue_wait_s < held.sent_unix + self.resend_after_s
                        or is_consumed(said, held.frame.run, held.frame.seq)
                        or beyond_known(said, held.frame.seq)):  # wait for a report that says
                    continue
                advanced = self._advanced.get(hop)
                if (said is report.consumed and held.frame.attempt == 0 and held.frame.seq > said.max_seq
                        and advanced is not None and report.t_unix - advanced < self.resend_after_s):
                    continue  # on its way behind the frames the consumer keeps receiving (a slow link)
                out.append((report.node, held))
        return out

    def held_back(self, frame: ChainFrame) -> None:
        """``frame``'s first send found no route: no copy of it has left this node."""
        held = self.hops.get((frame.chain, frame.target), {}).get((frame.run, frame.seq))
        if held is not None:
            held.on_air = False

    def resend(self, held: Held, now: float) -> tuple[ChainFrame, bool]:
        """The next copy of a held frame, as sent now, and whether it repeats one sent before.

        Rule: only a frame a copy of which has left this node is resent (its attempt number raised,
        counted in ``resent``, its radio and its consumer's run metered as recovery). A frame held
        back since it was produced, for want of a route, goes for the first time: its attempt
        stays 0 (no consumer can have it, so its output is no second copy either) and what it
        costs is the chain's steady work, which the model prices, not an overhead of the fault."""
        first = not held.on_air
        # A copy carries the hop's floor as it is now, not as it was at the first sending: a
        # consumer's fresh instance starts its gate at the lower of a frame's seq and its floor, and
        # an older floor would start it below frames that were acknowledged since and never come
        # again (it waited for them until it gave the gap up, with its producer backed up).
        frame = held.frame
        floor = frame.floor if frame.floor is None else self.floor(frame.chain, frame.target, frame.run, frame.seq)
        if not first:
            held.frame = replace(frame, attempt=frame.attempt + 1, floor=floor)
            self.resent += 1
        elif floor != frame.floor:
            held.frame = replace(frame, floor=floor)
        held.on_air = True
        held.sent_unix = now
        return held.frame, not first

    def frames(self) -> list[ChainFrame]:
        """Every frame held (what a clean stop leaves in flight: `autopower.node.in_flight`)."""
        return [held.frame for hop in self.hops.values() for held in hop.values()]

    def stats(self) -> dict[str, int]:
        return {"custody-frames": len(self), "custody-bytes": self.bytes, "custody-resent": self.resent,
                "custody-evicted": self.evicted, "custody-evicted-full": self.evicted_full,
                "custody-evicted-given-up": self.evicted_given_up, "results-kept-bytes": self.result_bytes,
                "dropped-by-budget": self.dropped_by_budget, "dropped-by-budget-bytes": self.dropped_by_budget_bytes}
