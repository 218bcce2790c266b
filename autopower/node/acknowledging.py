"""Acknowledging: custody of sent frames until their consumers report them consumed.

With every status a node sends one `Ack` to each node that feeds it (`acks`: what it took in
per hop of the chains that node sends or holds, `ack_interest`); producers release what was
acknowledged and resend what a later report still lacks.
"""

from __future__ import annotations

import logging

from autopower.node.custody import Report, hop_key, parse_hop_key
from autopower.node.stages import Lifecycle
from autopower.protocol import (
    Ack,
    ChainFrame,
    Consumed,
    NodeStatus,
    PeerStatus,
)

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class AckWants:
    """Which peers want the acknowledgements of which chains, as their last statuses said."""

    def __init__(self) -> None:
        self._by_peer: dict[str, frozenset[str]] = {}
        self._by_chain: dict[str, set[str]] = {}

    def update(self, peer: str, chains) -> None:
        new, old = frozenset(chains), self._by_peer.get(peer, frozenset())
        if new == old:
            return
        for chain in old - new:
            peers = self._by_chain[chain]
            peers.discard(peer)
            if not peers:
                del self._by_chain[chain]
        for chain in new - old:
            self._by_chain.setdefault(chain, set()).add(peer)
        self._by_peer[peer] = new

    def of(self, chain: str) -> set[str]:
        return self._by_chain.get(chain, set())


class Acknowledging:
    """The node's custody acknowledgements. Mixed into `NodeRuntime`, whose state it uses."""

    def on_ack(self, ack: Ack) -> None:
        """Another node's acknowledgement: what it consumed of a chain acknowledges what we sent it."""
        if ack.node == self.node:
            return
        now = self.wall()
        # a peer's word, bounded: custody gives a frame up after max_age_s whatever the wait
        wait = min(max(ack.queue_wait_s, 0.0), self.custody.max_age_s)
        # never newer than its arrival: a consumer whose clock runs ahead must not make
        # frames still in flight look lost
        self._acknowledge(ack.node, min(ack.t_unix, now), ack.consumed, wait, ack.older)
        self.resend_lost(now)

    def on_peer_status(self, status: NodeStatus | PeerStatus) -> None:
        """Another node's status: the chains whose acknowledgements it needs from us."""
        if status.node != self.node:
            self.ack_wants.update(status.node, status.acks_wanted)

    def acks(self, queue_wait_s: float = 0.0) -> dict[str, Ack]:
        """What this node consumed, as one `Ack` per node that sent us (or holds) frames of it.

        A chain's hops go to the producers the plan names for it (`producers_by_chain`) and to
        every peer whose last status says it wants them (it holds frames of that chain: a stage
        that moved away keeps its unacknowledged outputs; `ack_interest`). Nobody else hears them:
        a robot's acknowledgements grow with the chains it feeds, not with the team.
        """
        by_chain: dict[str, dict[str, Consumed]] = {}
        for key, report in self.consumed().items():
            by_chain.setdefault(parse_hop_key(key)[0], {})[key] = report
        if not by_chain:
            return {}
        to: dict[str, dict[str, Consumed]] = {}
        planned = self.producers_by_chain()
        for chain, hops in by_chain.items():
            dests = set(planned.get(chain, ()))
            dests.update(self.ack_wants.of(chain))
            for dest in dests - {self.node}:
                to.setdefault(dest, {}).update(hops)
        older = self.older_consumed()
        t_unix = self.wall()
        return {dest: Ack(node=self.node, t_unix=t_unix, consumed=consumed, queue_wait_s=queue_wait_s,
                          older={key: older[key] for key in consumed if key in older})
                for dest, consumed in sorted(to.items())}

    def older_consumed(self) -> dict[str, tuple[Consumed, ...]]:
        """Per sink hop, what the sink got of the older runs it remembers (`SinkLedger.older_reports`)."""
        out = {}
        for name, ledger in self.sinks.items():
            reports = ledger.older_reports()
            if reports and name in self.chains:
                out[hop_key(name, len(self.chains[name].stages))] = reports
        return out

    def ack_interest(self) -> set[str]:
        """The chains whose acknowledgements this node needs: those whose frames it may send.

        Its sources' chains, its stages' chains (their outputs), and every chain it holds frames
        of in custody (a stage that moved away leaves its unacknowledged outputs here). Our status
        says them (`NodeStatus.acks_wanted`); a consumer the plan does not name as our consumer
        sends us its acknowledgements once it has heard it.
        """
        out = set(self.custody.chains())
        out.update(self.sources)
        out.update(hosted.chain.name for hosted in self.hosted.values())
        return out

    def consumed(self, *, committed_sinks: bool = False) -> dict[str, Consumed]:
        """What this node's running stages and sinks have taken in, per hop. ``committed_sinks``: a
        sink's hop as of its last commit when it keeps its ledger on disk (`NodeRuntime.commit_sinks`):
        what a kill cannot take back."""
        out = {}
        for hosted in self.hosted.values():
            if hosted.lifecycle is Lifecycle.RUNNING:
                report = hosted.gate.report(hosted.run, hosted.generation)
                if report is not None:  # less the inputs still in the stage's worker (their outputs are not out)
                    out[hop_key(hosted.chain.name, hosted.index)] = self.acknowledged(hosted, report)
        for name, ledger in self.sinks.items():
            if committed_sinks and self.sink_store is not None:
                report = self._sinks_committed.get(name)
            else:
                report = ledger.report()
            if report is not None and name in self.chains:
                out[hop_key(name, len(self.chains[name].stages))] = report
        out.update(self.flows.consumed(self.hosted.values()))  # DAG flows: each fan-in stage's edge gates
        return out

    def _consumer_of(self, frame: ChainFrame) -> str | None:
        """Where the plan says the frame's consumer runs now (the next stage's host, or the sink)."""
        chain = self.chains[frame.chain]
        if frame.target >= len(chain.stages):
            return chain.sink
        return self.plan.placement.get(chain.stages[frame.target].name) if self.plan else None

    def producers(self) -> set[str]:
        """The nodes that send us frames now (a source or the previous stage's host)."""
        return set().union(*self.producers_by_chain().values())

    def producer_of(self, hosted) -> str | None:
        """The node the plan has feed a hosted stage: its chain's source, or the previous stage's host."""
        chain, index = hosted.chain, hosted.index
        if index == 0:
            return chain.source
        return self.plan.placement.get(chain.stages[index - 1].name) if self.plan else None

    def producers_by_chain(self) -> dict[str, set[str]]:
        """Per chain we consume, the nodes the plan has send us its frames: our acknowledgements
        (and our status) must reach them even when they are out of sight (relayed)."""
        placement = self.plan.placement if self.plan else {}
        out: dict[str, set[str]] = {}
        for hosted in self.hosted.values():
            out.setdefault(hosted.chain.name, set()).add(self.producer_of(hosted))
        for name in self.sinks:
            chain = self.chains.get(name)
            if chain is not None and chain.stages:
                out.setdefault(name, set()).add(placement.get(chain.stages[-1].name))
        for flow, producer in self.flows.producers(self.hosted.values(), self.plan).items():
            out.setdefault(flow, set()).add(producer)
        return {chain: nodes - {None, self.node} for chain, nodes in out.items() if nodes - {None, self.node}}

    def _acknowledge(self, node: str, t_unix: float, consumed: dict[str, Consumed],
                     queue_wait_s: float = 0.0, older: dict[str, tuple[Consumed, ...]] | None = None) -> None:
        for key, report in consumed.items():
            hop = parse_hop_key(key)
            if hop is None or hop[0] not in self.chains:
                self.count("garbled", f"{node} reports an unknown hop {key!r}")
                continue
            # a sink's older runs: only those before its current one count (a peer's word, checked)
            runs = {c.run: c for c in (older or {}).get(key, ()) if c.run < report.run}
            self.custody.on_report(hop[0], hop[1], Report(node=node, t_unix=t_unix, consumed=report,
                                                          queue_wait_s=queue_wait_s, older=runs))

    def resend_lost(self, now: float) -> None:
        """Resend what a consumer reported missing well after it was sent (throttled)."""
        if now < self._next_custody_check or self.network is None:
            return
        self._next_custody_check = now + 0.1
        for node, held in self.custody.due(now):
            if node != self._consumer_of(held.frame):
                continue  # the stage is moving: wait for its new host's report (it stays due)
            if not self.routable(node):
                continue  # no route yet: it stays due
            frame = self.custody.resend(held, now)
            self.tally("resent-frames")
            if frame.attempt == 1:
                log.info("%s: %s seq %d to stage %d was lost on the way to %s; resending", self.node, frame.chain,
                         frame.seq, frame.target, node)
            self.send_frame(frame, node, purpose="recovery")  # metered apart: not the plan's steady traffic

