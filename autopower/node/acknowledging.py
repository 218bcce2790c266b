"""Acknowledging: custody of sent frames until their consumers report them consumed.

With every status a node sends one `Ack` to each node that feeds it (`acks`: what it took in
per hop of the chains that node sends or holds, `ack_interest`); producers release what was
acknowledged and resend what a later report still lacks.

`Acknowledging` is a collaborator of `NodeRuntime`: it owns which peers want which chains'
acknowledgements (`AckWants`), when custody is next checked for resends, and what the sinks' ledgers
said at their last commit; it reads the node's plan, stages and custody through the runtime.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable

from autopower.node.custody import Report, hop_key, parse_hop_key
from autopower.node.sequencing import MAX_MISSING, ranges_of
from autopower.node.stages import HostedStage, Lifecycle
from autopower.node.workers import worker_of
from autopower.protocol import (
    Ack,
    ChainFrame,
    Consumed,
    NodeStatus,
    PeerStatus,
    decode,
    encode,
)
from autopower.protocol.access import addressed_problem

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
    """The node's custody acknowledgements: what it tells its producers, what it hears from its
    consumers, and the resends of what they report missing."""

    def __init__(self, rt):
        """``rt``: the `NodeRuntime` whose frames these are (its plan, stages, sinks and custody)."""
        self.rt = rt
        self.wants = AckWants()  # which peers want the acknowledgements of which chains
        self._next_check = 0.0  # wall: when custody is next checked for frames to resend (throttled)
        # per sink chain, what its ledger said at the last commit (`NodeRuntime.commit_sinks`): all this
        # node's own custody may let go of, between statuses
        self._sinks_committed: dict[str, Consumed] = {}

    def sinks_committed(self, reports: dict[str, Consumed]) -> None:
        """What the sinks' ledgers say as of the commit just made (`NodeRuntime.commit_sinks`)."""
        self._sinks_committed = reports

    def on_ack(self, ack: Ack) -> None:
        """Another node's acknowledgement: what it consumed of a chain acknowledges what we sent it."""
        if ack.node == self.rt.node:
            return
        now = self.rt.wall()
        # a peer's word, bounded: custody gives a frame up after max_age_s whatever the wait
        wait = min(max(ack.queue_wait_s, 0.0), self.rt.custody.max_age_s)
        # never newer than its arrival: a consumer whose clock runs ahead must not make
        # frames still in flight look lost
        self._acknowledge(ack.node, min(ack.t_unix, now), ack.consumed, wait, ack.older)
        self.resend_lost(now)

    def note_wants(self, status: NodeStatus | PeerStatus) -> None:
        """Another node's status: the chains whose acknowledgements it needs from us."""
        if status.node != self.rt.node:
            self.wants.update(status.node, status.acks_wanted)

    def tick(self, wall: float) -> None:
        """At the node's timer: what this node consumed itself acknowledges its own custody, and what
        its consumers report missing is resent (both at most every 0.1 s)."""
        if wall >= self._next_check:
            self._acknowledge(self.rt.node, wall, self.consumed(committed_sinks=True))
            self.resend_lost(wall)

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
            dests.update(self.wants.of(chain))
            for dest in dests - {self.rt.node}:
                to.setdefault(dest, {}).update(hops)
        older = self.older_consumed()
        t_unix = self.rt.wall()
        return {dest: Ack(node=self.rt.node, t_unix=t_unix, consumed=consumed, queue_wait_s=queue_wait_s,
                          older={key: older[key] for key in consumed if key in older})
                for dest, consumed in sorted(to.items())}

    def older_consumed(self) -> dict[str, tuple[Consumed, ...]]:
        """Per sink hop, what the sink got of the older runs it remembers (`SinkLedger.older_reports`)."""
        out = {}
        for name, ledger in self.rt.sinking.ledgers.items():
            reports = ledger.older_reports()
            if reports and name in self.rt.chains:
                out[hop_key(name, len(self.rt.chains[name].stages))] = reports
        return out

    def ack_interest(self) -> set[str]:
        """The chains whose acknowledgements this node needs: those whose frames it may send.

        Its sources' chains, its stages' chains (their outputs), and every chain it holds frames
        of in custody (a stage that moved away leaves its unacknowledged outputs here). Our status
        says them (`NodeStatus.acks_wanted`); a consumer the plan does not name as our consumer
        sends us its acknowledgements once it has heard it.
        """
        out = set(self.rt.custody.chains())
        out.update(self.rt.sources)
        out.update(hosted.chain.name for hosted in self.rt.hosted.values())
        return out

    def consumed(self, *, committed_sinks: bool = False) -> dict[str, Consumed]:
        """What this node's running stages and sinks have taken in, per hop. ``committed_sinks``: a
        sink's hop as of its last commit when it keeps its ledger on disk (`NodeRuntime.commit_sinks`):
        what a kill cannot take back."""
        out = {}
        for hosted in self.rt.hosted.values():
            if hosted.lifecycle is Lifecycle.RUNNING:
                report = hosted.gate.report(hosted.run, hosted.generation)
                if report is not None:  # less the inputs still in the stage's worker (their outputs are not out)
                    out[hop_key(hosted.chain.name, hosted.index)] = self.acknowledged(hosted, report)
                elif hosted.index > 0 or hosted.chain.sourced:  # (a first stage fed by flows only has no hop)
                    # Rule: a running instance reports its hop before its first input too (it has
                    # consumed nothing): its producer may hold frames for its dead predecessor, and one
                    # so backed up captures nothing new (`Custody.has_room`), so no first input would
                    # ever come to start the gate; told, it resends what it holds.
                    out[hop_key(hosted.chain.name, hosted.index)] = Consumed(
                        run=hosted.run, generation=hosted.generation, next_seq=0, max_seq=-1, missing=())
        for name, ledger in self.rt.sinking.ledgers.items():
            if committed_sinks and self.rt.sinking.store is not None:
                report = self._sinks_committed.get(name)
            else:
                report = ledger.report()
            if report is not None and name in self.rt.chains:
                out[hop_key(name, len(self.rt.chains[name].stages))] = report
        out.update(self.rt.flows.consumed(self.rt.hosted.values()))  # DAG flows: each fan-in stage's edge gates
        return out

    def _consumer_of(self, frame: ChainFrame) -> str | None:
        """Where the plan says the frame's consumer runs now (the next stage's host, or the sink)."""
        chain = self.rt.chains[frame.chain]
        if frame.target >= len(chain.stages):
            return chain.sink
        return self.rt.plan.placement.get(chain.stages[frame.target].name) if self.rt.plan else None

    def producers(self) -> set[str]:
        """The nodes that send us frames now (a source or the previous stage's host)."""
        return set().union(*self.producers_by_chain().values())

    def producer_of(self, hosted) -> str | None:
        """The node the plan has feed a hosted stage: its chain's source, or the previous stage's host."""
        chain, index = hosted.chain, hosted.index
        if index == 0:
            return chain.source
        return self.rt.plan.placement.get(chain.stages[index - 1].name) if self.rt.plan else None

    def producer_in_sight(self, hosted: HostedStage) -> bool:
        """Is the node that feeds ``hosted`` (its chain's source, or the previous stage's host) this
        one or in direct sight now: alive to resend what it holds?"""
        producer = self.producer_of(hosted)
        return producer is not None and (producer == self.rt.node or producer in self.rt.sight.alive)

    def producers_by_chain(self) -> dict[str, set[str]]:
        """Per chain we consume, the nodes the plan has send us its frames: our acknowledgements
        (and our status) must reach them even when they are out of sight (relayed)."""
        placement = self.rt.plan.placement if self.rt.plan else {}
        out: dict[str, set[str]] = {}
        for hosted in self.rt.hosted.values():
            out.setdefault(hosted.chain.name, set()).add(self.producer_of(hosted))
        for name in self.rt.sinking.ledgers:
            chain = self.rt.chains.get(name)
            if chain is not None and chain.stages:
                out.setdefault(name, set()).add(placement.get(chain.stages[-1].name))
        for flow, producer in self.rt.flows.producers(self.rt.hosted.values(), self.rt.plan).items():
            out.setdefault(flow, set()).add(producer)
        return {chain: nodes - {None, self.rt.node} for chain, nodes in out.items() if nodes - {None, self.rt.node}}

    def _acknowledge(self, node: str, t_unix: float, consumed: dict[str, Consumed],
                     queue_wait_s: float = 0.0, older: dict[str, tuple[Consumed, ...]] | None = None) -> None:
        for key, report in consumed.items():
            hop = parse_hop_key(key)
            if hop is None or hop[0] not in self.rt.chains:
                self.rt.count("garbled", f"{node} reports an unknown hop {key!r}")
                continue
            # a sink's older runs: only those before its current one count (a peer's word, checked)
            runs = {c.run: c for c in (older or {}).get(key, ()) if c.run < report.run}
            self.rt.custody.on_report(hop[0], hop[1], Report(node=node, t_unix=t_unix, consumed=report,
                                                          queue_wait_s=queue_wait_s, older=runs))

    def resend_lost(self, now: float) -> None:
        """Resend what a consumer reported missing well after it was sent (throttled)."""
        if now < self._next_check or self.rt.plan_view.network is None:
            return
        self._next_check = now + 0.1
        for node, held in self.rt.custody.due(now):
            if node != self._consumer_of(held.frame):
                continue  # the stage is moving: wait for its new host's report (it stays due)
            if not self.rt.frames.routable(node):
                continue  # no route yet: it stays due
            frame, again = self.rt.custody.resend(held, now)
            if not again:  # held back since it was produced (no route then): its first copy
                # metered as a backlog: the model priced no traffic of the chain while it had no route
                self.rt.tally("held-back-frames-sent")
                self.rt.frames.send_frame(frame, node, purpose="backlog")
                continue
            self.rt.tally("resent-frames")
            if frame.attempt == 1:
                log.info("%s: %s seq %d to stage %d was lost on the way to %s; resending", self.rt.node, frame.chain,
                         frame.seq, frame.target, node)
            self.rt.frames.send_frame(frame, node, purpose="recovery")  # metered apart: not the plan's steady traffic

    def acknowledged(self, hosted: HostedStage, report: Consumed) -> Consumed:
        """What a stage acknowledges to its producers: its gate's report less the inputs whose
        outputs are not safe yet (`_less_worker_held`, `_less_unsafe_outputs`)."""
        return self._less_unsafe_outputs(hosted, self._less_worker_held(hosted, report))

    def _less_unsafe_outputs(self, hosted: HostedStage, report: Consumed) -> Consumed:
        """An input whose output waits in this node's memory for its consumer's acknowledgement is
        reported had, not run (below ``max_seq``, not missing; ``next_seq`` lowered to it): its
        producer keeps it, and does not resend it while this instance reports it (`custody.is_run`).
        A crash of this node then takes the output but not the input: the stage's next instance,
        which reports it missing, gets it again and computes the output again (marked a resend:
        a sink that has it drops the copy). Outputs journaled to disk (results held for a sink out of
        reach, `Holds.hold`) are safe. While this node lives a lost output is still resent from its
        custody, never recomputed."""
        low = self.rt.holds.unsafe_floor(hosted.chain.name, hosted.index + 1, report.run)
        if low is None or low >= report.next_seq:
            return report
        return dataclasses.replace(report, next_seq=low)

    def _less_worker_held(self, hosted: HostedStage, report: Consumed) -> Consumed:
        """The gate's report less the inputs still in the stage's worker.

        In-process, a stage emits an input's output (into this node's custody) in the same step as
        its gate takes the input. In a worker the output comes later; until then the input stays
        unacknowledged, in its producer's custody: a node killed meanwhile loses none of them (its
        producer resends them to the stage's next instance) and the stage's sink sees each output
        once. A resend of one that is only slow is dropped by the gate (redundant)."""
        worker = worker_of(hosted.component)
        if worker is None:
            return report
        held = sorted({frame.seq for owner, frame in worker.outstanding()
                       if owner is hosted and frame.run == report.run and frame.seq < report.next_seq})
        if not held:
            return report
        # every held seq is below the gate's next_seq, every missing one at or above it: still sorted
        missing = list(ranges_of(held))
        if report.missing and report.missing[0][0] == missing[-1][1] + 1:  # adjacent: one range
            missing[-1] = (missing[-1][0], report.missing[0][1])
            missing += report.missing[1:]
        else:
            missing += report.missing
        return dataclasses.replace(report, next_seq=held[0], max_seq=max(report.max_seq, held[-1]),
                                   missing=tuple(missing[:MAX_MISSING]))

    def on_ack_message(self, key: str, payload: bytes) -> None:
        """An acknowledgement addressed to this node: checked (a forged or stale one is counted), then taken."""
        ack = decode(payload, Ack)
        problem = addressed_problem(self.rt.keys, key, ack.node, ack.t_unix, self.rt.wall())
        if problem is not None:
            self.rt.count("forged", problem)
            return
        self.on_ack(ack)

    def send(self, reachable: Callable[[str], bool], queue_wait_s: float = 0.0) -> int:
        """Send what this node consumed to the nodes that sent it (`acks`) and that ``reachable``
        (directly or relayed): the consumer's half of custody, sent with each status. Unreliable
        like the status (a saturated radio drops it rather than hold the loop up): the next
        status's acknowledgements say it again. Returns how many were sent."""
        sent = 0
        for dest, ack in self.acks(queue_wait_s).items():
            if reachable(dest):
                self.rt.send_to(dest, self.rt.keys.addressed(dest, self.rt.node), encode(ack), reliable=False)
                sent += 1
        return sent
