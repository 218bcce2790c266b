"""Frames: sending chain data along the model's routes, receiving it, running stages, sinking results.

A sender takes the shortest-hop route of the current network and puts it in the frame's header;
every node on the way forwards it and is charged for it. A stage runs each input once, in order
(its sequence gate); a sink counts each output once (its ledger, `autopower.node.sinks`).

`Frames` is a collaborator of `NodeRuntime`. It owns the chains' weights under the mission's
accounting; the routes are the plan's network, the frames kept for their consumers are custody's and
holds', and the stages are `Hosting`'s: it reads them through the runtime and leaves what it cannot
route to their owners (`Hosting.hold_orphan`, `Hosting.park`, `Holds.hold`).
"""

from __future__ import annotations

import dataclasses
import logging

from autopower.errors import ProtocolError
from autopower.node.guard import ComponentHung
from autopower.node.stages import MAX_FORWARDS, HostedStage, Lifecycle, pad
from autopower.node.workers import type_name, worker_of
from autopower.protocol import (
    ChainFrame,
    Packet,
    StateTransfer,
    decode,
    encode,
)

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class Frames:
    """The node's data plane: frames sent, forwarded and received, and the stages' inputs run."""

    def __init__(self, rt):
        """``rt``: the `NodeRuntime` whose data this is (its plan's routes, stages, custody and meter)."""
        self.rt = rt
        self.weights: dict[str, float] = {}  # per chain: the share of its bytes charged (`flow_weight`)

    def start(self, weights: dict[str, float]) -> None:
        """The mission starts: each chain's (and DAG flow's) weight under its accounting."""
        self.weights = weights

    def flush_held(self) -> None:
        """Send the held results whose sink the plan's network routes again (`Holds.flush`): metered as
        a backlog, as the model priced no traffic of theirs while their sink was out of reach."""
        self.rt.holds.flush(self.rt.plan_view.network,
                            lambda frame, sink: self.send_frame(frame, sink, purpose="backlog"))

    def join_stats(self) -> dict[str, dict[str, int]]:
        """Per fan-in stage hosted here: steps joined, inputs late, missing, empty steps."""
        return self.rt.flows.stats(self.rt.hosted)

    def join_tick(self) -> None:
        """Run the fan-in steps whose wait is over (from the node's timer). Without a flow in the
        scenario no stage joins inputs: nothing to look at (the base station's host runs a fleet's
        stages by the hundred, and this runs at every timer)."""
        if not self.rt.flows.fan_in:
            return
        speed, wall = self.rt.mission.speed if self.rt.mission else 1.0, self.rt.wall()
        for hosted in list(self.rt.hosted.values()):
            for frame in self.rt.flows.ready(hosted, self.rt.plan, speed, wall):
                self._run(hosted, frame)


    def emit(self, frame: ChainFrame, dest: str) -> None:
        """Send a frame this node produced, keeping it until its consumer acknowledges it."""
        frame = dataclasses.replace(frame, floor=self.rt.custody.floor(frame.chain, frame.target, frame.run, frame.seq))
        self.keep(frame)
        if not self.send_frame(frame, dest):
            self.rt.custody.held_back(frame)  # its first copy goes when a route does (`Custody.resend`)

    def keep(self, frame: ChainFrame) -> None:
        """Keep a frame this node is answerable for until its consumer acknowledges it: a chain's
        result within the hold budget until its sink has it, any other frame within custody's bounds."""
        if frame.target == len(self.rt.chains[frame.chain].stages):
            self.rt.holds.keep(frame)
        else:
            self.rt.custody.keep(frame, self.rt.wall())

    def send_frame(self, frame: ChainFrame, dest: str, forwards: int = 0, purpose: str = "chain") -> bool:
        """Send ``frame`` to ``dest`` (delivered here when it is this node); False if no route took it."""
        if dest == self.rt.node:
            self.deliver_frame(frame, forwards)
            return True
        chain = self.rt.chains[frame.chain]
        return self.send_routed(dest, encode(frame), chain.message_bytes[frame.target], self.weights[chain.name],
                                purpose, chain.name)

    def send_routed(self, dest: str, body: bytes, charge_bytes: int, weight: float, purpose: str,
                    chain: str) -> bool:
        path = self.rt.plan_view.network.path(self.rt.node, dest) if self.rt.plan_view.network else None
        if path is None:
            if purpose == "migration":
                self.rt.hosting.park(dest, body, chain)
                return False
            if purpose == "chain" and chain in self.rt.chains and dest == self.rt.chains[chain].sink:
                try:
                    frame = decode(body, ChainFrame)
                except ProtocolError:
                    frame = None
                if frame is not None and frame.target == len(self.rt.chains[chain].stages):
                    self.rt.holds.hold(frame)
                    return False
            self.rt.count("unroutable", f"no route from {self.rt.node} to {dest}")
            return False
        media = tuple(self.rt.plan_view.network.medium_between(u, v) for u, v in zip(path, path[1:], strict=False))
        packet = Packet(path=tuple(path), media=media, hop=1, charge_bytes=charge_bytes, weight=weight,
                        purpose=purpose, chain=chain, body=body)
        self.rt.meter.charge_radio("send", media[0], charge_bytes, weight, self.rt.now(), purpose, peer=path[1])
        wire = encode(packet)
        self.rt.control_plane.note_data(path[1], "send", len(wire))
        self.rt.send_to(path[1], self.rt.keys.node_data(path[1]), wire)
        return True

    def on_data(self, payload: bytes) -> None:
        packet = decode(payload, Packet)
        if not self.rt.started:
            self.rt.count("data-before-mission")
            return
        if packet.path[packet.hop] != self.rt.node:
            self.rt.count("misaddressed", f"packet for {packet.path[packet.hop]}")
            return
        for medium in packet.media:
            if medium not in self.rt.scenario.radios:
                raise ProtocolError(f"packet names unknown medium {medium!r}")
        now = self.rt.now()
        self.rt.meter.charge_radio("receive", packet.media[packet.hop - 1], packet.charge_bytes, packet.weight, now,
                                packet.purpose, peer=packet.path[packet.hop - 1])
        self.rt.control_plane.note_data(packet.path[packet.hop - 1], "receive", len(payload))
        if packet.hop < len(packet.path) - 1:  # a relay: pass it on, untouched
            nxt = Packet(path=packet.path, media=packet.media, hop=packet.hop + 1,
                         charge_bytes=packet.charge_bytes, weight=packet.weight, purpose=packet.purpose,
                         chain=packet.chain, body=packet.body)
            self.rt.meter.charge_radio("send", packet.media[packet.hop], packet.charge_bytes, packet.weight, now,
                                    packet.purpose, peer=packet.path[packet.hop + 1])
            wire = encode(nxt)
            self.rt.control_plane.note_data(packet.path[packet.hop + 1], "send", len(wire))
            self.rt.send_to(packet.path[packet.hop + 1], self.rt.keys.node_data(packet.path[packet.hop + 1]), wire)
            self.rt.tally("forwarded")
            return
        body = decode(packet.body, (ChainFrame, StateTransfer))
        if isinstance(body, StateTransfer):
            self.rt.hosting.on_state(body)
        else:
            self.deliver_frame(body)

    def deliver_frame(self, frame: ChainFrame, forwards: int = 0) -> None:
        chain = self.rt.chains.get(frame.chain)
        if chain is None or frame.target > len(chain.stages):
            self.rt.count("unknown-chain", f"{frame.chain} target {frame.target}")
            return
        if frame.target == len(chain.stages):
            self.rt.sinking.take(chain, frame)
            return
        stage = chain.stages[frame.target]
        hosted = self.rt.hosted.get(stage.name)
        if hosted is None:
            host = self.rt.plan.placement.get(stage.name) if self.rt.plan else None
            if host is not None and host != self.rt.node and forwards < MAX_FORWARDS and self.routable(host):
                self.rt.tally("rerouted")
                self.send_frame(frame, host, forwards + 1)
            elif host is None and (self.rt.plan is None or frame.chain not in self.rt.plan.running):
                self.rt.count("inactive-chain", f"{frame.chain} seq {frame.seq} arrived after its chain stopped",
                           logging.INFO)
            else:
                self.rt.hosting.hold_orphan(stage.name, frame)
            return
        if hosted.lifecycle is Lifecycle.FAILED:
            self.rt.count("failed-stage-input", f"{stage.name} seq {frame.seq}: its component has failed here",
                       logging.INFO)
        elif hosted.lifecycle is Lifecycle.STARTING:
            hosted.buffer.append(frame)
        elif hosted.lifecycle is Lifecycle.MIGRATED:
            if forwards >= MAX_FORWARDS or not self.routable(hosted.forward_to):
                # no route to its new host (yet): held here as an orphan, which the plan that
                # routes it there sends on (`on_plan`); its producer keeps it until a gate runs it
                self.rt.hosting.hold_orphan(stage.name, frame)
                return
            self.rt.tally("pointer-forwarded")
            self.send_frame(frame, hosted.forward_to, forwards + 1)
        else:
            self.admit(hosted, frame)

    def routable(self, dest: str) -> bool:
        """Whether the plan's network has a route from here to ``dest`` (this node always)."""
        return dest == self.rt.node or (self.rt.plan_view.network is not None and self.rt.plan_view.network.path(self.rt.node, dest) is not None)

    def admit(self, hosted: HostedStage, frame: ChainFrame, refusable: bool = True) -> None:
        """Offer an input to its stage's gate and run what it releases.

        ``refusable``: False for an input the stage's previous instance had already acknowledged
        (one of the inputs a migration carries): its producer no longer holds it, so it is taken
        even when the stage's worker is full."""
        if frame.chain != hosted.chain.name:  # a DAG flow into this stage: joined by step
            speed = self.rt.mission.speed if self.rt.mission else 1.0
            for ready in self.rt.flows.admit(hosted, frame, self.rt.plan, speed, self.rt.wall()):
                self._run(hosted, ready)
            return
        if frame.run != hosted.run:
            self.rt.count("stale-run", f"{hosted.stage.name}: frame of run {frame.run}, stage runs {hosted.run}",
                       logging.INFO)
            return
        if refusable and self._no_room(hosted, frame):
            return
        if hosted.lifecycle is Lifecycle.RUNNING and hosted.gate.skips_below(frame.floor) and hosted.carries_state():
            # an instance with state does not move past a gap on a floor: it starts afresh (`Hosting.start_afresh`)
            self.rt.hosting.start_afresh(hosted, frame.floor)
        before, redundant, skipped = hosted.gate.duplicates, hosted.gate.redundant, hosted.gate.skipped
        for ready in hosted.gate.offer(frame.seq, frame, frame.floor, resent=frame.attempt > 0, now=self.rt.wall()):
            self._run(hosted, ready)
        if hosted.gate.duplicates != before:
            self.rt.count("duplicate-input", f"{hosted.stage.name} seq {frame.seq}", logging.INFO)
        if hosted.gate.redundant != redundant:
            self.rt.tally("redundant-input")  # a resent copy of an input that was only late: dropped, as designed
        if hosted.gate.skipped != skipped:
            self.rt.count("inputs-given-up", f"{hosted.stage.name}: {hosted.gate.skipped - skipped} input(s) before "
                       f"seq {hosted.gate.next_seq} never arrived", logging.ERROR)

    def _run(self, hosted: HostedStage, frame: ChainFrame) -> None:
        chain = hosted.chain
        if hosted.lifecycle is Lifecycle.FAILED:
            return  # inputs already admitted in this batch when it failed
        worker = worker_of(hosted.component)
        if worker is not None:  # in its own process: handed over; `Components.collect_results` finishes it
            worker.submit((hosted, frame), frame.data())
            return
        started = self.rt.perf()
        # The component is code we do not control: whatever it does wrong stops this stage only.
        try:
            output = self.rt.guard.call(hosted.component.run, frame.data(), timeout_s=self.rt.components.hang_limit_s(chain))
        except ComponentHung as exc:
            self.rt.hosting.fail_stage(hosted, "hung", f"run(seq {frame.seq}): {exc}")
            return
        except Exception as exc:
            self.rt.hosting.fail_stage(hosted, "raised", f"run(seq {frame.seq}): {type(exc).__name__}: {exc}")
            return
        self.ran(hosted, frame, output, self.rt.perf() - started)

    def ran(self, hosted: HostedStage, frame: ChainFrame, output, compute_s: float) -> None:
        """A run's output (in-process or from its worker): checked, metered, emitted."""
        chain, index = hosted.chain, hosted.index
        target = index + 1
        if not isinstance(output, bytes):
            self.rt.hosting.fail_stage(hosted, "not-bytes", f"run(seq {frame.seq}) returned {type_name(output)}, not bytes")
            return
        if len(output) > chain.message_bytes[target]:
            self.rt.hosting.fail_stage(hosted, "oversize", f"run(seq {frame.seq}) returned {len(output)} B; the chain declares "
                            f"message_bytes {chain.message_bytes[target]} for this hop (raise it in the scenario)")
            return
        hosted.compute_s += compute_s
        hosted.runs += 1
        # A stage started without state recomputes what its lost predecessor may have sent already
        # (a repeated copy below its catch-up point: a first copy went to no instance before): an
        # overhead of the failover. An input captured before this host was named for the stage
        # waited through the reconfiguration (held for want of a route, or in the old host's gate):
        # the model priced its run where the stage was then, so running it here is a backlog,
        # metered apart from the plan's steady work. (The model prices a rate: from the change on,
        # the runs here are the inputs captured from then on, give or take the one in flight.)
        recomputed = hosted.gate.catch_up_below is not None and frame.seq < hosted.gate.catch_up_below \
            and frame.attempt > 0
        backlog = frame.t_virtual < hosted.placed_t
        purpose = "recovery" if recomputed else "backlog" if backlog else "chain"
        latency = self.rt.scenario.components[hosted.stage.component].latency_s[self.rt.platform.name]
        self.rt.meter.charge_run(latency, self.rt.now(), purpose)
        payload = pad(output, chain.message_bytes[target], f"{hosted.stage.name} output")
        # An input that came as a resend was resent because its acknowledgement had not come: the
        # instance it first went to may have run it and sent its output before it died or moved on.
        # This output is then a second copy of that one, and a retransmission made it: marked as
        # such, a sink that has the first drops it as redundant instead of delivering it again.
        again = recomputed or frame.attempt > 0
        out = ChainFrame(chain=chain.name, run=frame.run, seq=frame.seq, target=target, t_virtual=frame.t_virtual,
                         t_unix=frame.t_unix, payload_len=len(output), payload=payload, attempt=int(again))
        for flow_frame, flow_dest in self.rt.flows.fan_out(hosted, frame, output, self.rt.plan):
            self.emit(flow_frame, flow_dest)  # DAG fan-out: the same output along each flow it feeds
        dest = chain.sink if target == len(chain.stages) else self.rt.plan.placement.get(chain.stages[target].name)
        if dest is None:
            self.rt.count("unplaced-stage", f"{chain.stages[target].name} has no host")
            return
        self.emit(out, dest)

    # ---- stages in worker processes (`agent.workers`) -------------------------------------------------
    def _no_room(self, hosted: HostedStage, frame: ChainFrame) -> bool:
        """Refuse a new input, before its gate takes it, when the stage's worker is full (counted:
        ``stage-queue-full`` in the status's counters).

        Refused, it is not acknowledged: its producer keeps it in custody and resends it (after
        `custody.RESEND_AFTER_S`), so an overloaded worker delays inputs instead of losing them.
        A second copy is left to the gate (dropped there, not counted as refused), and so is every
        input while a gap is open in the gate: refusing those could refuse the very input the gate
        waits for (a full gate then waited for ever, seen live), and its own bounds (inputs, seconds)
        give the gap up. What the gap releases may take a worker past its bound, by at most those."""
        worker = worker_of(hosted.component)
        gate = hosted.gate
        if worker is None or gate.next_seq is None or frame.seq < gate.next_seq or gate.pending:
            return False
        if worker.room() > 0:
            return False
        self.rt.tally("stage-queue-full")  # a refusal, not a loss: counted with what happens, not with errors
        log.debug("%s: %s refused seq %d (its worker is full); its producer resends it", self.rt.node,
                  hosted.stage.name, frame.seq)
        return True

    def run_before_release(self, hosted: HostedStage, frames: list) -> None:
        """Run a released stage's waiting inputs, in order; their outputs go out as any does.

        A run that raises or hangs ends this (logged and counted: the stage is going anyway, and a
        failure reported now would stop its chain); what is left is lost, as before."""
        for done, frame in enumerate(frames):
            started = self.rt.perf()
            try:
                output = self.rt.guard.call(hosted.component.run, frame.data(),
                                         timeout_s=self.rt.components.hang_limit_s(hosted.chain))
            except Exception as exc:  # noqa: BLE001 - code we do not control; ComponentHung included
                self.rt.count("released-inputs-lost", f"{hosted.stage.name}: run(seq {frame.seq}) at release: "
                           f"{type(exc).__name__}: {exc}; {len(frames) - done} input(s) not run")
                return
            self.ran(hosted, frame, output, self.rt.perf() - started)
            self.rt.tally("released-inputs-run")
