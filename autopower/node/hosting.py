"""Hosting: the control messages that start, move and stop stages on this node.

Assign starts a fresh instance; Prepare readies an incoming one (inputs are buffered); MigrateOut
drains a running one and ships its state along the data path; the state arriving makes the new
instance RUNNING; Release retires one.

`Hosting` is a collaborator of `NodeRuntime`. It owns the stages hosted here (`HostedStage`), the
inputs held for a stage that has nowhere to go yet (orphans), the stages and sources that failed
here, the migration states parked for want of a route, the orders that came before the mission's
plan and the answers to a batch of orders. Components are built and retired by `Components`;
inputs are run along the data path (`Frames`).
"""

from __future__ import annotations

import dataclasses
import logging

from autopower.model.scenario import Chain
from autopower.node.sequencing import SequenceGate
from autopower.node.stages import ORPHAN_LIMIT, HostedStage, Lifecycle, placed_since
from autopower.node.workers import worker_of
from autopower.protocol import (
    Assign,
    ChainFrame,
    MigrateOut,
    NodeStatus,
    PeerStatus,
    Prepare,
    Prepared,
    Release,
    StageFailed,
    StageReady,
    StateTransfer,
    batched,
    decode,
    encode,
    unbatch,
)
from autopower.protocol.messages import CONTROL_MESSAGES

log = logging.getLogger("autopower.node.runtime")


class Hosting:
    """The node's stage lifecycle: the stages hosted here and what waits for them."""

    def __init__(self, rt):
        """``rt``: the `NodeRuntime` these stages run on (its plan, components and data path)."""
        self.rt = rt
        self.hosted: dict[str, HostedStage] = {}
        # inputs for a stage that has nowhere to go from here yet (bounded): sent on once a plan places it
        self.orphans: dict[str, list[ChainFrame]] = {}
        self.failed: dict[str, str] = {}  # stage -> why its component was stopped here (in every status)
        # migration state with no route yet (an order overtook the plan that brings the route
        # back): sent as soon as a plan routes it; never dropped, or the stage would be lost
        self.parked_transfers: list[tuple[str, bytes, str]] = []
        self._early_control: list[bytes] = []  # orders that came before the plan that starts the mission
        self._answer_batch: list[bytes] | None = None  # answers to a `Batch` of orders, sent as one (`on_control`)

    def on_control(self, payload: bytes) -> None:
        """An order, or a `Batch` of them (every item checked before any is carried out): the
        answers to one batch go back in one put."""
        orders = unbatch(payload, CONTROL_MESSAGES)
        if not self.rt.started:
            # The plan that starts the mission may arrive after the first orders (other key).
            if len(self._early_control) < 1000:
                self._early_control.append(payload)
            return
        if len(orders) == 1:
            # A lone order's answer goes out as soon as it is made, before the sends its handling
            # goes on to make (frames, state, resends): a reliable put on a link that went silent
            # blocks until the lease ends, and the answer must not wait behind it.
            self._on_order(orders[0][1])
            return
        self._answer_batch = []
        try:
            for _, msg in orders:
                self._on_order(msg)
        finally:
            answers, self._answer_batch = self._answer_batch, None
            if answers:
                self._to_basestation(batched(answers))

    def _on_order(self, msg) -> None:
        if msg.stage not in self.rt.stage_index:
            self.rt.count("unknown-stage", msg.stage)
            return
        if isinstance(msg, Assign):
            self.on_assign(msg)
        elif isinstance(msg, Prepare):
            self.on_prepare(msg)
        elif isinstance(msg, MigrateOut):
            self.on_migrate_out(msg)
        elif isinstance(msg, Release):
            self.on_release(msg)

    def _reply(self, msg) -> bytes:
        payload = encode(msg)
        self._to_basestation(payload)
        return payload

    def _to_basestation(self, payload: bytes) -> None:
        if self._answer_batch is not None:  # answering a batch of orders: the answers go together
            self._answer_batch.append(payload)
        else:
            self.rt.send_to(self.rt.scenario.basestation, self.rt.keys.inbox, payload)

    def _answer_again(self, hosted: HostedStage, order: str) -> None:
        """A repeated order this node has carried out already: its answer goes again, nothing is redone."""
        self.rt.tally("repeated-order")
        log.info("%s: %s for %s again (generation %d): answered again", self.rt.node, order, hosted.stage.name,
                 hosted.generation)
        if hosted.answer:
            self._to_basestation(hosted.answer)

    def _construct(self, msg, chain, stage):
        """A new instance of the stage's component, or None when its constructor raised (reported)."""
        try:
            return self.rt.components.new_component(chain, stage)
        except Exception as exc:
            self.rt.count("component-failed", f"{msg.stage}: {exc}", logging.ERROR)
            self._reply(StageFailed(stage=msg.stage, generation=msg.generation, node=self.rt.node, what="raised",
                                    detail=_bounded(f"constructor: {type(exc).__name__}: {exc}"), running=False))
            return None

    def follow_plan(self, plan) -> None:
        """A new plan: stages whose chain it runs in a newer run start afresh in it, a shipped state
        that has landed is known for it, and the inputs held for stages that landed elsewhere go there
        (those of a chain the operator stopped will never be consumed)."""
        self._follow_runs(plan)
        for hosted in self.hosted.values():
            if hosted.shipped and hosted.shipped[2] and plan.placement.get(hosted.stage.name) not in (None, self.rt.node):
                # it has landed (there, or on beyond): nobody will ask for its state again, and a
                # late copy of the order is known for one
                hosted.shipped = (*hosted.shipped[:2], b"")
        for stage, frames in list(self.orphans.items()):
            host = plan.placement.get(stage)
            chain = self.rt.stage_index.get(stage, (None, 0))[0]
            if chain is None or chain.name in plan.operator.disabled:
                del self.orphans[stage]
            elif host is not None and host != self.rt.node and self.rt.frames.routable(host):
                del self.orphans[stage]
                for frame in frames:
                    self.rt.frames.send_frame(frame, host)

    def placement_overridden(self, placement: dict[str, str]) -> None:
        """A placement agreed without the base station: the inputs held for a stage it puts elsewhere go there."""
        for stage, frames in list(self.orphans.items()):
            host = placement.get(stage)
            if host is not None and host != self.rt.node:
                del self.orphans[stage]
                for frame in frames:
                    self.rt.frames.send_frame(frame, host)

    def hold_orphan(self, stage: str, frame: ChainFrame) -> None:
        """Keep an input for ``stage`` that has nowhere to go from here yet (bounded)."""
        held = self.orphans.setdefault(stage, [])
        if len(held) >= ORPHAN_LIMIT:
            self.rt.count("orphan-overflow", f"{stage}: dropped seq {frame.seq}", logging.ERROR)
            return
        held.append(frame)

    def park(self, dest: str, body: bytes, chain: str) -> None:
        """A stage's state with no route to its new host yet: kept until a plan routes it (`send_parked`)."""
        self.parked_transfers.append((dest, body, chain))
        log.info("%s: no route to %s yet for %s's state; parked until a plan routes it", self.rt.node, dest, chain)

    def send_parked(self) -> None:
        """Send the parked states again (a new plan: those still without a route park again)."""
        parked, self.parked_transfers = self.parked_transfers, []
        for dest, body, chain in parked:
            self.rt.frames.send_routed(dest, body, len(body), 1.0, "migration", chain)

    def replay_early(self) -> None:
        """Carry out the orders that came before the plan that started the mission."""
        early, self._early_control = self._early_control, []
        for payload in early:
            self.on_control(payload)

    def source_failed(self, chain: Chain, detail: str) -> None:
        """A source here hung and was stopped: in every status from now on, and the base station is told."""
        self.failed[f"{chain.name} source"] = f"hung: {detail}"
        self.rt.count("source-failed", f"{chain.name}: hung: {detail}", logging.ERROR)
        self._reply(StageFailed(stage=chain.stages[0].name, generation=-1, node=self.rt.node, what="source-hung",
                                detail=detail, running=False))

    def _follow_runs(self, plan) -> None:
        """Start afresh, in the plan's run, a stage here whose chain the plan runs in a newer run.

        A chain restarted without state gets a new run (the base station's). An instance the base
        station then adopts as running (a subgroup had restarted it while the base station was
        away) keeps the old run and gets no order: its source follows the plan's new run, and the
        stage would drop every frame as stale-run, for good. A new run means the chain starts over,
        so the instance does: a fresh component and gate, same generation.
        """
        for name, hosted in list(self.hosted.items()):
            run = plan.running.get(hosted.chain.name)
            if (run is None or run <= hosted.run or hosted.lifecycle is not Lifecycle.RUNNING
                    or plan.placement.get(name) != self.rt.node):
                continue
            order = Assign(stage=name, generation=hosted.generation, chain=hosted.chain.name, run=run, resume_seq=None)
            component = self._construct(order, hosted.chain, hosted.stage)
            if component is None:
                continue
            self.rt.components.retire(hosted.component)
            self.rt.tally("stage-new-run")  # not an error: counted with what happens
            log.info("%s: %s runs in run %d, the plan's chain in run %d: started afresh in it", self.rt.node, name,
                     hosted.run, run)
            hosted.component, hosted.run, hosted.gate = component, run, SequenceGate()

    def start_afresh(self, hosted: HostedStage, floor: int) -> bool:
        """Start ``hosted`` afresh at ``floor``, its producer's floor that opens a gap in its gate: a
        fresh component and gate, same run and generation (False: its component is in a worker, or
        its constructor raised: it goes on as it was).

        Rule: an instance that carries state (`HostedStage.carries_state`) does not move past a gap on
        its producer's floor: when the floor rises above an input its gate waits for, it starts
        afresh there. A floor says that the producer no longer holds what is below it. That is what
        an instance of the stage ran, or what the producer lost: a producer that was killed lost its
        custody, and the restarted one sends what it makes next with its floor there (the frames only
        its process had died with it, `Resuming._died_in_hand`). The base station stops a chain whose source
        robot it lost, and the chain runs again with its stages started afresh (in its run when the
        robot's process holds its position, `basestation.runs`); but it may not
        see the robot go (a restart within the lease; a stale view of a relay: a keyframe of a
        status lost on a lossy link), and then the instance that waited for the dead input gets the
        restarted source's frames. Run past the gap, its component would take the next input as
        the one after the last it ran (the simulator's stand-ins refuse it, and the stage failed,
        its chain stopped until the operator enabled it). So it starts afresh at the floor, as the
        resumed chain would have: what it waited for is gone either way.

        The inputs waiting below the floor (they reached it, one before them had not) are run past
        the gap by the old instance before it goes, as a release runs them (`on_release`); those at
        or above it go to the fresh one. A component in a worker keeps going as it was (killing
        its worker would lose the inputs it is running, which its producer no longer holds)."""
        if worker_of(hosted.component) is not None:
            return False
        name = hosted.stage.name
        order = Assign(stage=name, generation=hosted.generation, chain=hosted.chain.name, run=hosted.run,
                       resume_seq=floor)
        component = self._construct(order, hosted.chain, hosted.stage)
        if component is None:
            return False
        old = hosted.gate
        waiting = old.take_pending()
        below = [frame for frame in waiting if frame.seq < floor]
        log.warning("%s: %s waited for seq %d; its producer no longer holds what is below seq %d: started afresh "
                    "there%s", self.rt.node, name, old.next_seq, floor,
                    f" ({len(below)} input(s) waiting below it run first)" if below else "")
        self.rt.tally("stage-started-afresh")
        if below:
            self.rt.frames.run_before_release(hosted, below)
        self.rt.components.retire(hosted.component)
        hosted.component, hosted.imported = component, False
        hosted.gate = SequenceGate(next_seq=floor)
        hosted.gate.resent.extend(old.resent)  # late originals of these are redundant here too
        for frame in waiting[len(below):]:  # already taken in once: never refused
            self.rt.frames.admit(hosted, frame, refusable=False)
        return True

    def on_assign(self, msg: Assign) -> None:
        chain, index = self.rt.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current and current.generation > msg.generation:
            return
        if current and current.generation == msg.generation and current.lifecycle is not Lifecycle.STARTING:
            self._answer_again(current, "Assign")  # a new instance would start its inputs over
            return
        component = self._construct(msg, chain, stage)
        if component is None:
            return
        self.failed.pop(msg.stage, None)
        if current is not None:
            self.rt.components.retire(current.component)
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.resume_seq), placed_t=placed_since(current, self.rt.now()))
        held = (current.buffer if current else []) + self.orphans.pop(msg.stage, [])
        self.hosted[msg.stage] = hosted
        hosted.answer = self._reply(StageReady(stage=msg.stage, generation=msg.generation, node=self.rt.node,
                                               imported_state=False, resume_seq=msg.resume_seq, downtime_ms=0.0,
                                               buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):  # held here (some acknowledged already): never refused
            self.rt.frames.admit(hosted, frame, refusable=False)

    def on_prepare(self, msg: Prepare) -> None:
        chain, index = self.rt.stage_index[msg.stage]
        current = self.hosted.get(msg.stage)
        if current is not None and current.generation > msg.generation:
            self.rt.tally("stale-order")  # a repeat that arrives after a newer order: it must change nothing
            return
        if current is not None and current.generation == msg.generation:
            self._answer_again(current, "Prepare")  # waiting for the state, or running with it already
            return
        if current is not None and current.lifecycle in (Lifecycle.RUNNING, Lifecycle.DRAINING):
            self.rt.count("prepare-while-running", msg.stage, logging.ERROR)
            return
        hosted = HostedStage(stage=chain.stages[index], chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.STARTING, placed_t=placed_since(current, self.rt.now()))
        hosted.buffer = self.orphans.pop(msg.stage, [])
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            hosted.buffer = current.buffer + hosted.buffer
        self.hosted[msg.stage] = hosted
        hosted.answer = self._reply(Prepared(stage=msg.stage, generation=msg.generation, node=self.rt.node))

    def on_migrate_out(self, msg: MigrateOut) -> None:
        hosted = self.hosted.get(msg.stage)
        if hosted is not None and hosted.shipped is not None and hosted.shipped[:2] == (msg.generation, msg.to_node):
            if not hosted.shipped[2]:  # it has landed there (the plan says so): a late copy of the order
                self.rt.tally("stale-order")
                return
            # shipped already: the state (or the new host's answer) was lost on the way; it goes again
            # as it was, and the new host imports it once
            self.rt.tally("state-resent")
            log.info("%s: MigrateOut of %s to %s again: its state sent again", self.rt.node, msg.stage, msg.to_node)
            self._ship(msg.to_node, hosted.shipped[2], hosted.chain.name)
            return
        if hosted is not None and hosted.generation > msg.generation:
            self.rt.tally("stale-order")  # a repeat that arrives after a newer order: it must change nothing
            return
        if hosted is None or hosted.lifecycle is not Lifecycle.RUNNING:
            self.rt.count("migrate-not-running", f"{msg.stage} is {hosted.lifecycle.value if hosted else 'absent'}",
                       logging.ERROR)
            return
        hosted.lifecycle = Lifecycle.DRAINING
        stopped_unix = self.rt.wall()  # downtime counts from here: checking the state is part of it
        # In-process runs are synchronous in this loop: the current one has finished. A stage in a
        # worker finishes its queued inputs first (their outputs go out as usual).
        if not self.rt.components.drain(hosted):
            return  # it failed while draining: stopped here, the base station told (StageFailed)
        refused = self.rt.components.exportable_state(hosted)
        if isinstance(refused, tuple):  # the stage keeps running here; the base station is told
            what, detail = refused
            hosted.lifecycle = Lifecycle.RUNNING
            self.rt.count(what, f"{msg.stage}: {detail}", logging.ERROR)
            self._reply(StageFailed(stage=msg.stage, generation=msg.generation, node=self.rt.node, what=what,
                                    detail=_bounded(f"migration to {msg.to_node} refused: {detail}"), running=True))
            return
        state = refused
        pending = tuple(hosted.gate.take_pending())
        # The outputs of inputs run here that only this node's memory holds go along: ``next_seq`` says
        # their inputs were run, so their producer lets them go once the new host reports it.
        outputs = tuple(self.rt.holds.unsafe_frames(hosted.chain.name, hosted.index + 1, hosted.run))
        transfer = StateTransfer(stage=msg.stage, generation=msg.generation, chain=hosted.chain.name,
                                 run=hosted.run, state=state, next_seq=hosted.gate.next_seq, pending=pending,
                                 t_export_unix=stopped_unix, from_node=self.rt.node,
                                 resent=hosted.gate.recent_resends(), outputs=outputs)
        body = encode(transfer)
        hosted.lifecycle = Lifecycle.MIGRATED
        hosted.forward_to = msg.to_node
        hosted.shipped = (msg.generation, msg.to_node, body)
        self.rt.components.retire(hosted.component)
        hosted.component = None
        self.rt.plan_view.stage_left(msg.stage, msg.to_node)  # it runs there from now on, not here
        self._ship(msg.to_node, body, hosted.chain.name)

    def _ship(self, to_node: str, body: bytes, chain: str) -> None:
        # The state crosses the network like any message: routed, forwarded, charged (real bytes).
        if to_node == self.rt.node:
            self.on_state(decode(body, StateTransfer))
        else:
            self.rt.frames.send_routed(to_node, body, len(body), 1.0, "migration", chain)

    def on_state(self, msg: StateTransfer) -> None:
        if msg.stage not in self.rt.stage_index:
            self.rt.count("unknown-stage", msg.stage)
            return
        chain, index = self.rt.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current is not None and current.generation > msg.generation:
            # a second copy of a state (its sender was asked again) arriving after a newer order
            self.rt.tally("stale-state")
            return
        if current is not None and current.generation == msg.generation and current.lifecycle is not Lifecycle.STARTING:
            # imported already (its sender was asked again): importing it twice would run inputs twice
            if current.lifecycle is Lifecycle.RUNNING:
                self._answer_again(current, "StateTransfer")
            else:
                self.rt.tally("repeated-order")
            return
        imported = True
        component = None
        try:
            component = self.rt.components.new_component(chain, stage)
            self.rt.components.import_state(component, msg.state, chain)
        except Exception as exc:
            self.rt.components.retire(component)
            # It imported on the old host (checked before it was shipped), so this host runs other
            # code. The old instance is gone: go on here without the state, from where it stopped.
            self.rt.count("import-failed", f"{msg.stage}: {exc}", logging.ERROR)
            self._reply(StageFailed(stage=msg.stage, generation=msg.generation, node=self.rt.node, what="import-failed",
                                    detail=_bounded(f"state from {msg.from_node} did not import, started without "
                                                    f"it: import_state: {type(exc).__name__}: {exc}"), running=True))
            imported = False
            component = self._construct(msg, chain, stage)
            if component is None:
                return
        held = list(msg.pending)
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            held += current.buffer
        held += self.orphans.pop(msg.stage, [])
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.next_seq), placed_t=placed_since(current, self.rt.now()))
        hosted.gate.resent.extend(msg.resent)  # late originals of these are redundant here too
        hosted.imported = imported
        self._adopt_outputs(msg, hosted)
        self.failed.pop(msg.stage, None)
        if current is not None:
            self.rt.components.retire(current.component)
        self.hosted[msg.stage] = hosted
        hosted.answer = self._reply(StageReady(
            stage=msg.stage, generation=msg.generation, node=self.rt.node, imported_state=imported,
            resume_seq=msg.next_seq, downtime_ms=max(0.0, (self.rt.wall() - msg.t_export_unix) * 1e3), buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):  # held here (some acknowledged already): never refused
            self.rt.frames.admit(hosted, frame, refusable=False)

    def _adopt_outputs(self, msg: StateTransfer, hosted: HostedStage) -> None:
        """Keep in custody the outputs the old host had not had acknowledged (`StateTransfer.outputs`),
        as sent already: resent from here only if their consumer reports them missing (the old host
        died with them, or a restarted sink had not written them down). Marked resends: a consumer
        that has one drops the copy as redundant."""
        target = hosted.index + 1
        for frame in msg.outputs:
            if frame.chain != msg.chain or frame.target != target or frame.run != msg.run:
                self.rt.count("garbled", f"{msg.from_node} moved {msg.stage} with an output of {frame.chain} "
                                      f"stage {frame.target} run {frame.run}, not of this stage")
                continue
            self.rt.frames.keep(dataclasses.replace(frame, attempt=max(frame.attempt, 1)))
        if msg.outputs:
            self.rt.tally("outputs-adopted", len(msg.outputs))

    def fail_stage(self, hosted: HostedStage, what: str, detail: str) -> None:
        """Stop a stage whose component misbehaved; the node and its other stages go on.

        The stage stays here as FAILED (its inputs are dropped and counted) until the base
        station releases it; the failure is in every status (``failed``) until the stage is
        assigned here again, and the base station is told at once.
        """
        name = hosted.stage.name
        text = _bounded(f"{what}: {detail}")
        self.rt.components.retire(hosted.component)
        hosted.lifecycle, hosted.failure, hosted.component = Lifecycle.FAILED, text, None
        self.failed[name] = text
        self.rt.count("stage-failed", f"{name}: {text}", logging.ERROR)
        self._reply(StageFailed(stage=name, generation=hosted.generation, node=self.rt.node, what=what,
                                detail=_bounded(detail), running=False))

    def on_release(self, msg: Release) -> None:
        """Stop hosting a stage. The inputs waiting in its gate behind a gap are left to their
        producer, run here first, or kept.

        Producers keep a stage's input until a gate has run it (custody's `is_run`). While the
        producer says it still holds the gap (`SequenceGate.held_upstream`) and is in sight, it
        holds what waits behind it too, and sends them to the stage's next instance in order:
        nothing is run here (running them past the gap would deliver later outputs and lose the
        gap's for good). Otherwise (the producer gave the gap up, or is gone), an in-process stage gives the
        gap up and runs them, in order, before it stops: their outputs go on as any output does (a
        sink out of reach holds them). A stage in a worker keeps them as orphans (sent to the
        stage's host once a plan places it). A chain the operator stopped, or whose component
        failed, drops them.

        A chain stopped by a fault resumes its run when its source robot's process holds the run's
        position (`basestation.runs`): a producer only out of
        sight still holds the gap and what waits behind it, and sends them to the next instance
        (whose outputs of them are marked resends: a sink that has these drops them); a producer
        that was killed took the gap with it, and this is the only run those inputs get.

        A starting instance (prepared for a state that did not come) keeps the inputs it buffered as
        orphans too: a subgroup round that restarts the stage on another member sends them there.
        """
        hosted = self.hosted.get(msg.stage)
        if hosted is not None and hosted.generation <= msg.generation:
            held_upstream = hosted.gate.held_upstream(self.rt.wall()) and self.rt.acknowledging.producer_in_sight(hosted)
            waiting = hosted.gate.take_pending()
            if waiting and held_upstream:
                # their producer holds the gap and everything after it until a gate runs them
                # (custody): it sends them to the stage's next instance, in order
                log.info("%s: %s released with %d input(s) waiting behind a gap its producer holds; left to it",
                         self.rt.node, msg.stage, len(waiting))
            elif waiting and not self._disabled(hosted.chain.name):
                if worker_of(hosted.component) is None and hosted.lifecycle is Lifecycle.RUNNING:
                    hosted.gate.skipped += waiting[0].seq - (hosted.gate.next_seq or waiting[0].seq)
                    log.info("%s: %s released with %d input(s) waiting behind a gap; run before it stops",
                             self.rt.node, msg.stage, len(waiting))
                    self.rt.frames.run_before_release(hosted, waiting)
                else:
                    self.orphans.setdefault(msg.stage, []).extend(waiting)
                    log.info("%s: %s released with %d input(s) waiting; kept for its next instance", self.rt.node,
                             msg.stage, len(waiting))
            if hosted.buffer:  # a starting instance's inputs, held for its state: its successor's
                self.orphans.setdefault(msg.stage, []).extend(hosted.buffer)
            self.rt.components.retire(hosted.component)
            self.hosted.pop(msg.stage, None)  # a failing run may have dropped it already
        chain = self.rt.stage_index.get(msg.stage, (None, 0))[0]
        if chain is None or self._disabled(chain.name):
            self.orphans.pop(msg.stage, None)

    def yield_to_newer(self, status: NodeStatus | PeerStatus) -> bool:
        """Stop an instance here that a newer one running on the peer ``status`` comes from supersedes;
        True when one stopped (the process says so in its status at once).

        A round this robot was not part of (frozen or cut off at the time) may have restarted one of
        its stages elsewhere. Back in reach, its own instance gets no inputs any more (the source sends
        to the newer one), while its model would count the work all the same. Generations order
        instances (the base station's orders, rounds' wall-clock milliseconds), so the older one stops.
        Only against a RUNNING peer: a STARTING one may be a migration's new host, whose state this
        instance has yet to ship. Inputs waiting in its gate (already acknowledged to their producers)
        go to the newer instance, which drops those it has.
        """
        stopped = False
        for stage, state in (status.hosted or {}).items():
            mine = self.hosted.get(stage)
            theirs = (status.generations or {}).get(stage)
            if (mine is None or theirs is None or state != Lifecycle.RUNNING.value
                    or mine.lifecycle is not Lifecycle.RUNNING or theirs <= mine.generation):
                continue
            waiting = mine.gate.take_pending()
            log.warning("%s: %s runs on %s as a newer instance (generation %d, this one %d): stopped here%s",
                        self.rt.node, stage, status.node, theirs, mine.generation,
                        f"; its {len(waiting)} waiting input(s) go there" if waiting else "")
            self.rt.tally("superseded-instances")
            self.on_release(Release(stage=stage, generation=mine.generation))
            self.rt.plan_view.override_placement({stage: status.node}, set())
            for frame in waiting:
                self.rt.frames.send_frame(frame, status.node)
            stopped = True
        return stopped

    def _disabled(self, chain: str) -> bool:
        """The operator stopped the chain (or its component failed): nobody will consume its inputs."""
        return self.rt.plan is None or chain in self.rt.plan.operator.disabled


def _bounded(text: str, limit: int = 300) -> str:
    """One line of at most ``limit`` characters (an exception text travels in status and messages)."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 1] + "…"
