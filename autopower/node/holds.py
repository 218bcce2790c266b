"""Holds: the results a node keeps for a sink it cannot reach, in order, within the hold budget.

A result whose sink has no route from here (the plan's links) is held: kept in custody like every
frame this node sends (`autopower.node.custody`), counted against the node's hold budget with the
rest of its custody (the oldest results go first, counted and told as "budget"), and journaled on
disk when the process has a `HeldStore`, so that a crash loses none. A chain that keeps only its
latest result (``keep = "latest"``) holds one per run: the older ones are let go as "superseded".
The held results go to their sink as soon as a route returns (`flush`), as retransmissions: the
sink may have had one from another instance meanwhile, and then drops the copy as redundant.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import OrderedDict
from typing import Callable

from autopower.model.network import Network
from autopower.model.scenario import Chain
from autopower.node.custody import Custody
from autopower.node.held_store import HeldStore
from autopower.node.ports import SinkListeners
from autopower.protocol import ChainFrame

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts

HeldKey = tuple[str, int, int, int]  # (chain, target, run, seq)


def held_key(frame: ChainFrame) -> HeldKey:
    return frame.chain, frame.target, frame.run, frame.seq


class Holds:
    """The node's held results. It owns them (in the order they were held), how many were let go
    and why, and which are on disk; it shares the node's `Custody`, which keeps every result until
    its sink acknowledges it. ``chain`` names a chain of the node's (None: not one), ``wall`` is the
    node's wall clock and ``tally`` its event counter; ``listeners`` hear of each result let go;
    ``mission_key`` says the running mission's key, which the journal names."""

    def __init__(self, *, node: str, custody: Custody, store: HeldStore | None, chain: Callable[[str], Chain | None],
                 listeners: SinkListeners, tally: Callable[..., None], wall: Callable[[], float],
                 mission_key: Callable[[], dict | None]):
        self._node = node
        self._custody = custody
        self.store = store  # the journal on disk (None: a crash loses what is held)
        self._chain = chain
        self._listeners = listeners
        self._tally = tally
        self._wall = wall
        self._mission_key = mission_key  # the running mission's key (`resuming.mission_key`; None before it)
        self.held: OrderedDict[HeldKey, ChainFrame] = OrderedDict()
        self.dropped = 0  # results let go, the hold budget full (counted apart from lost ones)
        self.superseded = 0  # results of a latest-only chain replaced in the hold by a newer one
        self._journaled: dict[HeldKey, ChainFrame] = {}

    def __len__(self) -> int:
        return len(self.held)

    def hold(self, frame: ChainFrame) -> None:
        """Hold a result whose sink is out of reach (journaled under the mission's key once it is known)."""
        # Sent late, as a retransmission: the sink may have had this output meanwhile from another
        # instance (a released stage runs the inputs waiting in its gate, while their producer, its
        # acknowledgement cut off, resends them to the stage's next instance). A restarted sink does
        # not keep on disk what came as a resend, so an unmarked held copy arriving later would be
        # taken as new and delivered twice. Marked, a sink that has it drops it as redundant.
        frame = dataclasses.replace(frame, attempt=max(frame.attempt, 1))
        self.held[held_key(frame)] = frame
        self._supersede(frame)
        self.keep(frame, sent=False)  # in custody already when produced here (`emit`)
        self._custody.mark(frame, None)  # not on the wire: no resend is due until it is
        self._journal(frame, self._mission_key())
        if len(self.held) == 1:
            log.info("%s: the sink of %s is out of reach; holding its results here (within %.0f MB, oldest "
                     "dropped beyond) until a plan routes them", self._node, frame.chain,
                     self._custody.hold_budget_bytes / 2**20)

    def keep(self, frame: ChainFrame, sent: bool = True) -> None:
        """Keep a chain's result in custody until its sink acknowledges it; results beyond the hold
        budget (oldest first) are dropped and counted as such."""
        for dropped in self._custody.keep(frame, self._wall(), sent=sent, result=True):
            self.held.pop(held_key(dropped), None)
            self.dropped += 1
            self._tally("held-outputs-dropped")
            self._listeners.held_dropped(dropped.chain, dropped.run, dropped.seq, "budget")

    def _supersede(self, newest: ChainFrame) -> None:
        """A chain that keeps only its latest result (`keep = "latest"`) holds one per run for its sink:
        the older ones this node held are let go, counted as superseded (the replay counts one so only
        if a later output of its run reached the sink or was in hand at the stop; else it is lost)."""
        chain = self._chain(newest.chain)
        if chain is None or chain.keep != "latest":
            return
        older = [frame for frame in self.held.values()
                 if frame.chain == newest.chain and frame.run == newest.run and frame.seq < newest.seq]
        for frame in older:
            del self.held[held_key(frame)]
            self._custody.forget(frame)
            self.superseded += 1
            self._tally("held-outputs-superseded")
            self._listeners.held_dropped(frame.chain, frame.run, frame.seq, "superseded")

    def _journal(self, frame: ChainFrame, mission_key: dict | None) -> None:
        key = held_key(frame)
        if self.store is None or mission_key is None or key in self._journaled:
            return
        if self.store.append(mission_key, frame):  # not on disk: a crash here loses it
            self._journaled[key] = frame

    def unsafe_floor(self, chain: str, target: int, run: int) -> int | None:
        """The lowest seq of a hop and run this node holds in custody in memory only (not journaled):
        what a crash here would lose unless its input is still held upstream; None if none is."""
        low = self._custody.floor(chain, target, run, -1)
        if low < 0:
            return None
        if (chain, target, run, low) not in self._journaled:
            return low
        held = self.unsafe_frames(chain, target, run)
        return held[0].seq if held else None

    def unsafe_frames(self, chain: str, target: int, run: int) -> list[ChainFrame]:
        """The frames of a hop and run this node holds in custody in memory only, by seq (what
        `unsafe_floor` is the lowest of)."""
        hop = self._custody.hops.get((chain, target), {})
        return [held.frame for (r, seq), held in sorted(hop.items())
                if r == run and (chain, target, run, seq) not in self._journaled]

    def settle_store(self) -> None:
        """Drop from the disk the held results that are done with (acknowledged by their sink, or
        let go by a full hold): the file is rewritten with the rest once most of it is done with,
        emptied once all of it is (`autopower.node.held_store`). At each status tick."""
        mission_key = self._mission_key()
        if self.store is None or mission_key is None or not self._journaled:
            return
        at_risk = {key: frame for key, frame in self._journaled.items()
                   if (frame.run, frame.seq) in self._custody.hops.get((frame.chain, frame.target), {})}
        if len(at_risk) == len(self._journaled):
            return
        self._journaled = at_risk
        if not at_risk or self.store.records > 2 * len(at_risk) + 64:
            self.store.rewrite(mission_key, list(at_risk.values()))

    def take_back(self, mission_key: dict) -> None:
        """A restarted process takes back the results the crashed one held (same mission only)."""
        if self.store is None:
            return
        journal = [f for f in self.store.load(mission_key) if self._chain(f.chain) is not None]
        # Each goes again as the retransmission `hold` journaled it as: the crashed process may have
        # delivered it, and its sink acknowledged it, before the journal was next rewritten (at a
        # status tick); a sink that has it drops the copy as redundant, where a copy sent as new
        # would be delivered twice.
        for frame in journal:
            self.held[held_key(frame)] = frame
            self._supersede(frame)  # a latest-only chain: journaled before the older ones were let go
            self.keep(frame, sent=False)  # within this process's budget (oldest dropped, counted)
        frames = list(self.held.values())
        if self.store.rewrite(mission_key, frames):  # this process's journal from now on
            self._journaled.update((held_key(frame), frame) for frame in frames)
        if frames:
            spans = {}
            for frame in frames:
                low, high = spans.get(frame.chain, (frame.seq, frame.seq))
                spans[frame.chain] = (min(low, frame.seq), max(high, frame.seq))
            log.warning("%s: took back %d result(s) held before the restart (%s); they go to their sink once "
                        "it is in reach", self._node, len(frames),
                        ", ".join(f"{c} seq {low}-{high}" for c, (low, high) in sorted(spans.items())))

    def flush(self, network: Network | None, send: Callable[[ChainFrame, str], None]) -> None:
        """Send each held result whose sink ``network`` routes again (``send(frame, sink)``), in order."""
        if not self.held or network is None:
            return
        held, self.held = self.held, OrderedDict()
        sent = 0
        for key, frame in held.items():
            sink = self._chain(frame.chain).sink
            if network.path(self._node, sink) is None:
                self.held[key] = frame
            else:
                send(frame, sink)
                self._custody.mark(frame, self._wall())
                sent += 1
        if sent:
            log.info("%s: delivered %d held result(s)", self._node, sent)
            self._tally("held-outputs-delivered", sent)
