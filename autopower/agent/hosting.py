"""Hosting: the control messages that start, move and stop stages on this node.

Assign starts a fresh instance; Prepare readies an incoming one (inputs are buffered); MigrateOut
drains a running one and ships its state along the data path; the state arriving makes the new
instance RUNNING; Release retires one.
"""

from __future__ import annotations

import logging
import time

from autopower.agent.sequencing import SequenceGate
from autopower.agent.stages import HostedStage, Lifecycle, chain_seed
from autopower.model.scenario import Chain, Stage
from autopower.protocol import (
    Assign,
    MigrateOut,
    Prepare,
    Prepared,
    Release,
    StageReady,
    StateTransfer,
    decode,
    encode,
)
from autopower.protocol.messages import CONTROL_MESSAGES


class Hosting:
    """The node's stage lifecycle. Mixed into `NodeRuntime`, whose state it uses."""

    def on_control(self, payload: bytes) -> None:
        msg = decode(payload, CONTROL_MESSAGES)
        if not self.started:
            # The plan that starts the mission may arrive after the first orders (other key).
            if len(self._early_control) < 1000:
                self._early_control.append(payload)
            return
        if msg.stage not in self.stage_index:
            self.count("unknown-stage", msg.stage)
            return
        if isinstance(msg, Assign):
            self.on_assign(msg)
        elif isinstance(msg, Prepare):
            self.on_prepare(msg)
        elif isinstance(msg, MigrateOut):
            self.on_migrate_out(msg)
        elif isinstance(msg, Release):
            self.on_release(msg)

    def _new_component(self, chain: Chain, stage: Stage):
        return self._make_component(stage.component, chain.source, chain_seed(self.scenario, chain))

    def _reply(self, msg) -> None:
        self.send_to(self.scenario.basestation, self.keys.inbox, encode(msg))

    def on_assign(self, msg: Assign) -> None:
        chain, index = self.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current and current.generation > msg.generation:
            return
        try:
            component = self._new_component(chain, stage)
        except Exception as exc:
            self.count("component-failed", f"{msg.stage}: {exc}", logging.ERROR)
            return
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.resume_seq))
        held = (current.buffer if current else []) + self.orphans.pop(msg.stage, [])
        self.hosted[msg.stage] = hosted
        self._reply(StageReady(stage=msg.stage, generation=msg.generation, node=self.node, imported_state=False,
                               resume_seq=msg.resume_seq, downtime_ms=0.0, buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):
            self._admit(hosted, frame)

    def on_prepare(self, msg: Prepare) -> None:
        chain, index = self.stage_index[msg.stage]
        current = self.hosted.get(msg.stage)
        if current is not None and current.lifecycle in (Lifecycle.RUNNING, Lifecycle.DRAINING):
            self.count("prepare-while-running", msg.stage, logging.ERROR)
            return
        hosted = HostedStage(stage=chain.stages[index], chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.STARTING)
        hosted.buffer = self.orphans.pop(msg.stage, [])
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            hosted.buffer = current.buffer + hosted.buffer
        self.hosted[msg.stage] = hosted
        self._reply(Prepared(stage=msg.stage, generation=msg.generation, node=self.node))

    def on_migrate_out(self, msg: MigrateOut) -> None:
        hosted = self.hosted.get(msg.stage)
        if hosted is None or hosted.lifecycle is not Lifecycle.RUNNING:
            self.count("migrate-not-running", f"{msg.stage} is {hosted.lifecycle.value if hosted else 'absent'}",
                       logging.ERROR)
            return
        # The current run has finished: runs are synchronous in this loop.
        hosted.lifecycle = Lifecycle.DRAINING
        try:
            state = hosted.component.export_state()
        except Exception as exc:
            self.count("export-failed", f"{msg.stage}: {exc}", logging.ERROR)
            hosted.lifecycle = Lifecycle.RUNNING
            return
        pending = tuple(hosted.gate.take_pending())
        transfer = StateTransfer(stage=msg.stage, generation=msg.generation, chain=hosted.chain.name,
                                 run=hosted.run, state=state, next_seq=hosted.gate.next_seq, pending=pending,
                                 t_export_unix=time.time(), from_node=self.node,
                                 resent=hosted.gate.recent_resends())
        body = encode(transfer)
        hosted.lifecycle = Lifecycle.MIGRATED
        hosted.forward_to = msg.to_node
        hosted.component = None
        # The state crosses the network like any message: routed, forwarded, charged (real bytes).
        if msg.to_node == self.node:
            self.on_state(transfer)
        else:
            self.send_routed(msg.to_node, body, len(body), 1.0, "migration", hosted.chain.name)

    def on_state(self, msg: StateTransfer) -> None:
        if msg.stage not in self.stage_index:
            self.count("unknown-stage", msg.stage)
            return
        chain, index = self.stage_index[msg.stage]
        stage = chain.stages[index]
        current = self.hosted.get(msg.stage)
        if current is not None and current.generation > msg.generation:
            self.count("stale-state", f"{msg.stage} generation {msg.generation}")
            return
        try:
            component = self._new_component(chain, stage)
            component.import_state(msg.state)
        except Exception as exc:
            self.count("import-failed", f"{msg.stage}: {exc}", logging.ERROR)
            return
        held = list(msg.pending)
        if current is not None and current.lifecycle is Lifecycle.STARTING:
            held += current.buffer
        held += self.orphans.pop(msg.stage, [])
        hosted = HostedStage(stage=stage, chain=chain, index=index, generation=msg.generation,
                             lifecycle=Lifecycle.RUNNING, run=msg.run, component=component,
                             gate=SequenceGate(next_seq=msg.next_seq))
        hosted.gate.resent.extend(msg.resent)  # late originals of these are redundant here too
        self.hosted[msg.stage] = hosted
        self._reply(StageReady(stage=msg.stage, generation=msg.generation, node=self.node, imported_state=True,
                               resume_seq=msg.next_seq, downtime_ms=max(0.0, (time.time() - msg.t_export_unix) * 1e3),
                               buffered=len(held)))
        for frame in sorted(held, key=lambda f: f.seq):
            self._admit(hosted, frame)

    def on_release(self, msg: Release) -> None:
        hosted = self.hosted.get(msg.stage)
        if hosted is not None and hosted.generation <= msg.generation:
            del self.hosted[msg.stage]
        self.orphans.pop(msg.stage, None)

