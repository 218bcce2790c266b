"""Sinks: the outputs that reach this node as their chain's sink, each counted and handed on once.

`Sinks` is a collaborator of `NodeRuntime`. It owns a ledger per sink chain (`SinkLedger`: what
arrived, in which run, with which latency), the last output of each, and where the ledgers are kept
across a restart (`SinkStore`: the base station's, in its team state directory), so that an output
delivered before a crash is not delivered again after it. It tells the runtime's `SinkListeners` of
each output.
"""

from __future__ import annotations

import logging
import zlib

from autopower.model.scenario import Chain
from autopower.node.ports import SinkListeners
from autopower.node.sequencing import SinkLedger
from autopower.node.sink_store import SinkStore
from autopower.protocol import ChainFrame, Consumed, SinkStats

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class Sinks:
    """This node's sink ledgers and their store."""

    def __init__(self, rt, store: SinkStore | None, listeners: SinkListeners):
        """``rt``: the `NodeRuntime` these sinks are on; ``store``: where the ledgers are kept across a
        restart (None: in memory only); ``listeners``: who hears of each output."""
        self.rt = rt
        self._listeners = listeners
        self.ledgers: dict[str, SinkLedger] = {}
        self.last_output: dict[str, bytes] = {}
        self.store = store

    def load(self, epoch_unix: float) -> None:
        """The mission starts: a restarted sink goes on from what it had delivered."""
        if self.store is not None:
            self.ledgers.update(self.store.load(epoch_unix))

    def replay_journal(self) -> None:
        """Tell the listeners what the last commit before a restart delivered (at mission time)."""
        if self.store is not None:
            for chain, run, seq in self.store.last_batch:
                self._listeners.sink_journal(chain, run, seq)

    def take(self, chain: Chain, frame: ChainFrame) -> None:
        """An output of ``chain`` reaching this node, its sink: counted once in its ledger, handed on once."""
        if chain.sink != self.rt.node:
            self.rt.count("wrong-sink", f"{chain.name} output reached {self.rt.node}")
            return
        ledger = self.ledgers.setdefault(chain.name, SinkLedger())
        latency_ms = (self.rt.wall() - frame.t_unix) * 1000.0
        redundant, duplicates = ledger.redundant_total, ledger.duplicates_total
        new = ledger.record(frame.run, frame.seq, latency_ms, frame.data(), frame.attempt)
        if new and self.store is not None and self.rt.mission is not None:
            # noted now, written out with the status that acknowledges it (`SinkStore.commit`)
            self.store.keep(self.rt.mission.epoch_unix, self.ledgers, chain.name, frame.run, frame.seq,
                                 zlib.crc32(frame.data()))
        if not new:
            if ledger.redundant_total != redundant:
                self.rt.tally("redundant-output")  # a resent copy of what arrived late: dropped, as designed
                return
            if ledger.duplicates_total != duplicates or frame.run >= ledger.run:
                # The operator gets each output once: any other second copy means it was produced
                # (or carried) twice. Counted (the ledger's `duplicates_total` goes with the status
                # into the recording and the replay's invariants), never handed on. This holds for
                # the last runs before the current one too (`SinkLedger.older`).
                self.rt.count("duplicate-output", f"{chain.name} run {frame.run} seq {frame.seq}", logging.ERROR)
                return
            # an older run's output, late or resent after its chain started over, is no error (its
            # run is over at this sink): handed on once, the recording shows it
            self.rt.count("stale-output", f"{chain.name} run {frame.run} seq {frame.seq}", logging.INFO)
        elif frame.attempt:
            self.rt.tally("recovered-outputs")  # lost in flight, delivered by a resend
        self.last_output[chain.name] = frame.data()
        if self._listeners:
            self._listeners.output(chain.name, frame.run, frame.seq, frame.data())

    def commit(self) -> dict[str, Consumed]:
        """Write down what the sinks took in since the last commit; what each ledger says now."""
        if self.store is not None:
            self.store.commit()
        return {name: report for name, ledger in self.ledgers.items() if (report := ledger.report()) is not None}

    def close(self, *, commit: bool = True) -> None:
        """Close the store (``commit`` False: the notes since the last commit are not written)."""
        if self.store is not None:
            self.store.close(commit=commit)

    def stats(self) -> dict[str, SinkStats]:
        """Each sink's ledger as the status reports it."""
        return {n: SinkStats(run=l.run, received=l.received, duplicates=l.duplicates, contiguous=l.contiguous,
                             max_seq=l.max_seq, stale=l.stale, latency_ms_p50=l.latency_ms_p50,
                             latency_ms_max=l.latency_ms_max, received_total=l.received_total,
                             duplicates_total=l.duplicates_total, digest=l.digest,
                             redundant_total=l.redundant_total, given_up_total=l.given_up_total)
                for n, l in self.ledgers.items()}
