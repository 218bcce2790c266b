"""Acknowledging: custody of sent frames until their consumers report them consumed.

A node's status carries what it consumed per hop; producers read their consumers' statuses,
release what was acknowledged and resend what a later report still lacks.
"""

from __future__ import annotations

import logging

from autopower.node.custody import Report, hop_key, parse_hop_key
from autopower.node.stages import Lifecycle
from autopower.protocol import (
    ChainFrame,
    Consumed,
    NodeStatus,
)

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class Acknowledging:
    """The node's custody acknowledgements. Mixed into `NodeRuntime`, whose state it uses."""

    def on_peer_status(self, status: NodeStatus) -> None:
        """Another node's status: what it consumed acknowledges what we sent it."""
        if status.node == self.node:
            return
        now = self.wall()
        # a peer's word, bounded: custody gives a frame up after max_age_s whatever the wait
        wait = min(max(status.queue_wait_s, 0.0), self.custody.max_age_s)
        # never newer than its arrival: a consumer whose clock runs ahead must not make
        # frames still in flight look lost
        self._acknowledge(status.node, min(status.t_unix, now), status.consumed, wait)
        self.resend_lost(now)

    def consumed(self) -> dict[str, Consumed]:
        """What this node's running stages and sinks have taken in, per hop."""
        out = {}
        for hosted in self.hosted.values():
            if hosted.lifecycle is Lifecycle.RUNNING:
                report = hosted.gate.report(hosted.run, hosted.generation)
                if report is not None:  # less the inputs still in the stage's worker (their outputs are not out)
                    out[hop_key(hosted.chain.name, hosted.index)] = self.acknowledged(hosted, report)
        for name, ledger in self.sinks.items():
            report = ledger.report()
            if report is not None and name in self.chains:
                out[hop_key(name, len(self.chains[name].stages))] = report
        out.update(self.flow_consumed())  # DAG flows: each fan-in stage's edge gates
        return out

    def _consumer_of(self, frame: ChainFrame) -> str | None:
        """Where the plan says the frame's consumer runs now (the next stage's host, or the sink)."""
        chain = self.chains[frame.chain]
        if frame.target >= len(chain.stages):
            return chain.sink
        return self.plan.placement.get(chain.stages[frame.target].name) if self.plan else None

    def producers(self) -> set[str]:
        """The nodes that send us frames now (a source or the previous stage's host): our status
        acknowledges their frames, so it must reach them even when they are out of sight."""
        placement = self.plan.placement if self.plan else {}
        out = set()
        for hosted in self.hosted.values():
            chain, index = hosted.chain, hosted.index
            out.add(chain.source if index == 0 else placement.get(chain.stages[index - 1].name))
        for name in self.sinks:
            chain = self.chains.get(name)
            if chain is not None and chain.stages:
                out.add(placement.get(chain.stages[-1].name))
        out |= self.flow_producers()
        return out - {None, self.node}

    def _acknowledge(self, node: str, t_unix: float, consumed: dict[str, Consumed],
                     queue_wait_s: float = 0.0) -> None:
        for key, report in consumed.items():
            hop = parse_hop_key(key)
            if hop is None or hop[0] not in self.chains:
                self.count("garbled", f"{node} reports an unknown hop {key!r}")
                continue
            self.custody.on_report(hop[0], hop[1], Report(node=node, t_unix=t_unix, consumed=report,
                                                          queue_wait_s=queue_wait_s))

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

