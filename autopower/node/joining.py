"""Joining: DAG flows at run time (docs/concepts/chains.md).

A flow (`autopower.model.dag.Flow`) carries a producer stage's output to a stage of another chain.
On the wire it is a hop of its own: frames of pseudo-chain ``flow.name`` ("Loc-1>TeamMap"), target
0, numbered by the producer chain's (run, seq). So every flow is kept in custody by its producer
until the consumer acknowledges it, resent if lost, and admitted at most once by its consumer
(one `EdgeGate` per flow): each input is delivered exactly once.

The join rule: a fan-in stage runs once per *step* (step = the producer's tick time / period; all
sources tick on the mission clock's multiples of the period, so equal steps are the same moment).
A step runs, in step order, as soon as every expected input (those whose producer chain runs) is
there; an input that has not come `join_wait_s` wall seconds after the step's first input is
declared *missing* and the step runs with what is present, the absent producers listed in the
join message (`autopower.chains.teammap.encode_join`) and counted: "join-missing" (an error) when
that edge had delivered an input for an earlier step, "join-not-started" (a counter) when it had
not (sources start a period or two apart when a team starts). A producer whose first output (seq
0 of its run) came for a later step is not waited for at all: its input for this step never comes. An input that arrives
after its step ran is *late*: consumed (acknowledged, never run twice), dropped and counted
("join-late"). A step none of whose inputs came is skipped (`Frames.join_stats`: empty_steps).
The bound is above the custody resend time (about 1 s), so a lost frame that a resend recovers in
time still joins its own step.

The join's state (edge gates, waiting inputs, next step, steps joined) is part of the stage's
exported state: a fan-in stage migrates with it (`JoinedComponent`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, Mapping

import msgpack

from autopower.chains.teammap import encode_join
from autopower.errors import ProtocolError
from autopower.model.dag import Flow
from autopower.model.energy import flow_weight
from autopower.model.scenario import Chain, Scenario
from autopower.node.custody import hop_key
from autopower.node.sequencing import missing_between
from autopower.node.stages import HostedStage, Lifecycle, pad
from autopower.protocol import ChainFrame, Consumed, PlanUpdate

log = logging.getLogger("autopower.node.runtime")

JOIN_WAIT_MIN_S = 3.0  # wall seconds: above custody's resend (RESEND_AFTER_S = 1 s) and a status round
JOIN_WAIT_PERIODS = 1.5  # ... and at least this many of the chain's periods (in wall time)
MAX_WAITING_STEPS = 256  # steps held waiting for inputs (bounded memory)
STATE_VERSION = 1


def join_wait_s(period_s: float, speed: float) -> float:
    return max(JOIN_WAIT_MIN_S, JOIN_WAIT_PERIODS * period_s / max(speed, 1e-9))


def flow_chains(scenario: Scenario) -> dict[str, Chain]:
    """A pseudo-chain per flow, so its frames travel, are charged and kept like a chain hop:
    one stage (the consumer), its input `flow.n_bytes` long, the producer chain's period."""
    by_stage = {s.name: (c, s) for c in scenario.chains for s in c.stages}
    out = {}
    for chain in scenario.chains:
        for flow in chain.inputs:
            producer_chain = by_stage[flow.producer][0]
            out[flow.name] = Chain(name=flow.name, source=producer_chain.source, sink="", period_s=producer_chain.period_s,
                                   stages=(by_stage[flow.consumer][1],), message_bytes=(flow.n_bytes, 0))
    return out


@dataclass
class EdgeGate:
    """Exactly-once admission of one flow's frames, in any order (a lost one must not hold the
    others back: the join decides what is late). Reports like a sink (`Consumed`), so the
    producer's custody releases what came and resends what is missing."""

    run: int = -1
    contiguous: int = 0
    above: set[int] = field(default_factory=set)
    duplicates: int = 0

    def admit(self, run: int, seq: int, floor: int | None = None) -> str:
        """"new", "duplicate" or "stale" (a frame of an older run of the producer chain).

        ``floor`` is the producer's lowest unacknowledged seq (`ChainFrame.floor`): everything below
        was consumed by some instance of this stage, so a gate started fresh (a failover without
        state) starts there instead of asking for the whole run again."""
        if run < self.run:
            return "stale"
        if run > self.run:
            self.run, self.contiguous, self.above = run, 0 if floor is None else min(seq, floor), set()
        elif floor is not None and floor > self.contiguous and not any(s < floor for s in self.above):
            self.contiguous = floor  # consumed by a previous instance
        if seq < self.contiguous or seq in self.above:
            self.duplicates += 1
            return "duplicate"
        self.above.add(seq)
        while self.contiguous in self.above:
            self.above.remove(self.contiguous)
            self.contiguous += 1
        return "new"

    def report(self, generation: int) -> Consumed | None:
        if self.run < 0:
            return None
        top = max(self.above, default=self.contiguous - 1)
        return Consumed(run=self.run, generation=generation, next_seq=self.contiguous, max_seq=top,
                        missing=missing_between(self.contiguous, top, self.above))


@dataclass
class Join:
    """One step's inputs, ready to run."""

    step: int
    payload: bytes
    missing: list[str]  # producers absent from this step (all of them, as the join message lists them)
    lost: list[str]  # ... of which had delivered before: a loss; the others had not started yet
    t_unix: float  # the earliest input's production time (latency counts from there)


class JoinState:
    """The waiting inputs of one fan-in stage and where its join stands."""

    def __init__(self, flows: tuple[Flow, ...]):
        self.flows = {f.name: f for f in flows}
        self.gates: dict[str, EdgeGate] = {name: EdgeGate() for name in self.flows}
        self.waiting: dict[int, dict[str, tuple[bytes, float]]] = {}  # step -> flow -> (data, t_unix)
        self.first_seen: dict[int, float] = {}  # step -> wall time its first input came
        self.next_step: int | None = None
        # when each producer started: a step before that is "not started", not a loss
        self.first_step: dict[str, int] = {}  # flow -> the earliest step it delivered an input for
        self.began: dict[str, tuple[int, int]] = {}  # flow -> (run, step) of its latest run's seq 0
        self.joined = 0
        self.late = 0
        self.missing = 0  # inputs absent from a step whose edge had delivered before
        self.not_started = 0  # inputs absent because their producer had not produced anything yet
        self.empty_steps = 0

    def offer(self, flow: str, frame: ChainFrame, step: int, now: float) -> str:
        """Admit one input: "new", "duplicate", "stale", "late" or "overflow"."""
        verdict = self.gates[flow].admit(frame.run, frame.seq, frame.floor)
        if verdict != "new":
            return verdict
        self.first_step[flow] = min(step, self.first_step.get(flow, step))
        if frame.seq == 0 and frame.run >= self.began.get(flow, (-1, 0))[0]:
            self.began[flow] = (frame.run, step)
        if self.next_step is not None and step < self.next_step and self.started:
            self.late += 1
            return "late"
        if step not in self.waiting and len(self.waiting) >= MAX_WAITING_STEPS:
            return "overflow"
        if self.next_step is None or step < self.next_step:
            # Before any step ran, the first step is the earliest input seen: producers' first
            # inputs arrive in any order (each crosses its own route), so an earlier step's input
            # that comes second opens the join; it is not late.
            self.next_step = step
        self.waiting.setdefault(step, {})[flow] = (frame.data(), frame.t_unix)
        self.first_seen.setdefault(step, now)
        return "new"

    def ready(self, expected: set[str], now: float, wait_s: float) -> list[Join]:
        """The steps that may run now, in order (see the module docstring for the rule)."""
        out = []
        while self.next_step is not None and self.waiting:
            k = self.next_step
            inputs = self.waiting.get(k)
            if inputs is None:  # nothing came for step k: skip it once a later step has waited long enough
                oldest = min(self.waiting)
                if now - self.first_seen[oldest] < wait_s:
                    break
                self.empty_steps += oldest - k
                self.next_step = oldest
                continue
            absent = sorted(expected - set(inputs))
            awaited = [name for name in absent if not self.starts_after(name, k)]
            if awaited and now - self.first_seen[k] < wait_s:
                break
            del self.waiting[k]
            del self.first_seen[k]
            lost = [name for name in absent if self.delivered_before(name, k)]
            self.missing += len(lost)
            self.not_started += len(absent) - len(lost)
            producers = {self.flows[name].producer: data for name, (data, _) in inputs.items()}
            out.append(Join(step=k, missing=[self.flows[name].producer for name in absent],
                            lost=[self.flows[name].producer for name in lost],
                            payload=encode_join(k, producers, [self.flows[name].producer for name in absent]),
                            t_unix=min(t for _, t in inputs.values())))
            self.joined += 1
            self.next_step = k + 1
        return out

    @property
    def started(self) -> bool:
        """A step ran or was skipped: every step below `next_step` is closed, so an input for one
        is late. Until then `next_step` is only the earliest step an input came for."""
        return self.joined > 0 or self.empty_steps > 0

    def starts_after(self, flow: str, step: int) -> bool:
        """The flow's producer certainly began after ``step``: the first output of its run (seq 0)
        came, for a later step (an older run's frames are stale once a newer one came). Its input
        for ``step`` will never come: the step need not wait for it."""
        began = self.began.get(flow)
        return began is not None and began[0] == self.gates[flow].run and began[1] > step

    def delivered_before(self, flow: str, step: int) -> bool:
        """The flow had delivered an input for a step before ``step``: its absence is a loss (or a
        late input). Otherwise its producer had not started yet (start-up: sources begin a period
        or two apart), whatever came for later steps since."""
        return self.first_step.get(flow, step) < step

    def consumed(self, generation: int) -> dict[str, Consumed]:
        out = {}
        for name, gate in self.gates.items():
            report = gate.report(generation)
            if report is not None:
                out[hop_key(name, 0)] = report
        return out

    # ---- migration -------------------------------------------------------------------------------
    def export(self, now: float | None = None) -> dict:
        """The join's state; waiting inputs' ages are taken at ``now`` (the node's wall time)."""
        now = time.time() if now is None else now
        return {"gates": {n: [g.run, g.contiguous, sorted(g.above)] for n, g in self.gates.items()},
                "waiting": [[k, n, d, t] for k, inputs in self.waiting.items() for n, (d, t) in inputs.items()],
                "first_seen_age": {str(k): now - t for k, t in self.first_seen.items()},
                "next_step": self.next_step,
                "first_step": self.first_step, "began": {n: list(b) for n, b in self.began.items()},
                "counts": [self.joined, self.late, self.missing, self.empty_steps, self.not_started]}

    def restore(self, obj: dict, now: float | None = None) -> None:
        gates = obj["gates"]
        if set(gates) != set(self.flows):
            raise ValueError(f"join state for flows {sorted(gates)}, this stage has {sorted(self.flows)}")
        for name, (run, contiguous, above) in gates.items():
            self.gates[name] = EdgeGate(run=int(run), contiguous=int(contiguous), above={int(s) for s in above})
        self.waiting, self.first_seen = {}, {}
        now = time.time() if now is None else now
        for k, name, data, t in obj["waiting"]:
            if name not in self.flows or not isinstance(data, bytes):
                raise ValueError(f"join state: bad waiting input {name!r}")
            self.waiting.setdefault(int(k), {})[name] = (data, float(t))
        for k, age in obj["first_seen_age"].items():
            self.first_seen[int(k)] = now - float(age)
        self.next_step = None if obj["next_step"] is None else int(obj["next_step"])
        first_step, began = obj.get("first_step", {}), obj.get("began", {})  # absent from an older node's state
        if not set(first_step) <= set(self.flows) or not set(began) <= set(self.flows):
            raise ValueError(f"join state: start steps of unknown flows {sorted({*first_step, *began} - set(self.flows))}")
        self.first_step = {name: int(step) for name, step in first_step.items()}
        self.began = {name: (int(run), int(step)) for name, (run, step) in began.items()}
        self.joined, self.late, self.missing, self.empty_steps, self.not_started = (int(v) for v in obj["counts"])


class JoinedComponent:
    """A fan-in stage's component with its join: `run` is the inner component's; the exported
    state carries both, so the stage migrates with its waiting inputs and edge gates."""

    def __init__(self, inner, flows: tuple[Flow, ...], wall: Callable[[], float] = time.time):
        self.inner = inner
        self.join = JoinState(flows)
        self.wall = wall  # the node's wall clock: the join's ages travel relative to it

    def run(self, payload: bytes) -> bytes:
        return self.inner.run(payload)

    def export_state(self) -> bytes:
        inner = self.inner.export_state() if callable(getattr(self.inner, "export_state", None)) else b""
        if not isinstance(inner, bytes):
            raise TypeError(f"export_state returned {type(inner).__name__}, not bytes")
        return msgpack.packb({"v": STATE_VERSION, "inner": inner, "join": self.join.export(self.wall())}, use_bin_type=True)

    def import_state(self, state: bytes) -> None:
        obj = msgpack.unpackb(state, raw=False, strict_map_key=False)
        if not isinstance(obj, dict) or obj.get("v") != STATE_VERSION:
            raise ValueError("not a fan-in stage's state")
        if obj["inner"] or callable(getattr(self.inner, "import_state", None)):
            self.inner.import_state(obj["inner"])
        self.join.restore(obj["join"], self.wall())


class Flows:
    """The scenario's DAG flows as one node sees them: fan-out of a stage's output along the flows it
    feeds, and fan-in of a stage's inputs by step (`JoinedComponent`).

    It owns the flows' layout, read once from the scenario (who feeds whom, the pseudo-chain each
    flow travels as). It is given the plan, the stages hosted here and the wall time with each
    call, and returns what the node must do: the frames to send (`fan_out`) and the inputs a join
    released to run (`admit`, `ready`). ``count`` and ``tally`` are the node's error and event
    counters; ``joined(chain, run, seq)`` hears of each input a join step makes."""

    def __init__(self, scenario: Scenario, *, count: Callable[..., None], tally: Callable[..., None],
                 joined: Callable[[str, int, int], None]):
        self.chains = flow_chains(scenario)  # a flow's frames travel like a chain hop's
        self._count = count
        self._tally = tally
        self._joined = joined
        self._out: dict[str, list[Flow]] = {}  # producing stage -> the flows it feeds
        self._in: dict[str, tuple[Flow, ...]] = {}  # consuming stage -> the flows into it
        for chain in scenario.chains:
            for flow in chain.inputs:
                self._out.setdefault(flow.producer, []).append(flow)
                self._in[flow.consumer] = (*self._in.get(flow.consumer, ()), flow)
        self._chain_of = {s.name: c for c in scenario.chains for s in c.stages}

    def weights(self, accounting: str) -> dict[str, float]:
        return {f.name: flow_weight(self._chain_of[f.producer], accounting)
                for flows in self._out.values() for f in flows}

    @property
    def fan_in(self) -> bool:
        """Does a stage of the scenario take a flow (and so may wait to join its inputs, `ready`)?"""
        return bool(self._in)

    def running(self, plan: PlanUpdate | None) -> set[str]:
        """The flows whose producer's and consumer's chains both run."""
        running = plan.running if plan else {}
        return {f.name for flows in self._out.values() for f in flows
                if self._chain_of[f.producer].name in running and self._chain_of[f.consumer].name in running}

    def wrap(self, component, stage_name: str, wall: Callable[[], float]):
        """A fan-in stage's component with the join of its flows (its state travels with it)."""
        flows = self._in.get(stage_name)
        return JoinedComponent(component, flows, wall) if flows else component

    # ---- producer side: fan-out ------------------------------------------------------------------
    def fan_out(self, hosted: HostedStage, frame: ChainFrame, output: bytes,
                plan: PlanUpdate) -> list[tuple[ChainFrame, str]]:
        """A stage's output (already sent to its own successor) as a frame for each running flow it
        feeds, with where the plan runs that flow's consumer."""
        running = self.running(plan)
        out = []
        for flow in self._out.get(hosted.stage.name, ()):
            if flow.name not in running:
                continue
            if len(output) > flow.n_bytes:
                self._count("flow-oversize", f"{flow.name}: {len(output)} B, the flow declares {flow.n_bytes} B "
                            "(raise its bytes in the scenario)", logging.ERROR)
                continue
            dest = plan.placement.get(flow.consumer)
            if dest is None:
                self._count("unplaced-stage", f"{flow.consumer} has no host")
                continue
            out.append((ChainFrame(chain=flow.name, run=frame.run, seq=frame.seq, target=0,
                                   t_virtual=frame.t_virtual, t_unix=frame.t_unix, payload_len=len(output),
                                   payload=pad(output, flow.n_bytes, flow.name), attempt=frame.attempt), dest))
            self._tally("flow-frames")
        return out

    # ---- consumer side: fan-in -------------------------------------------------------------------
    def admit(self, hosted: HostedStage, frame: ChainFrame, plan: PlanUpdate | None, speed: float,
              wall: float) -> Iterator[ChainFrame]:
        """Offer a flow's frame to its stage's join (now); then the inputs the stage's gate releases,
        as `ready` gives them."""
        component = hosted.component
        if not isinstance(component, JoinedComponent) or frame.chain not in component.join.flows:
            self._count("unexpected-flow", f"{frame.chain} at {hosted.stage.name}")
            return iter(())
        period = hosted.chain.period_s
        step = int(round(frame.t_virtual / period))
        verdict = component.join.offer(frame.chain, frame, step, wall)
        if verdict == "duplicate" and frame.attempt:
            self._tally("redundant-input")  # a resent copy of an input that was only late
        elif verdict == "duplicate":
            self._count("duplicate-input", f"{frame.chain} seq {frame.seq}", logging.INFO)
        elif verdict == "late":
            self._count("join-late", f"{hosted.stage.name}: {frame.chain} step {step} came after its step ran",
                        logging.INFO)
        elif verdict in ("stale", "overflow"):
            self._count(f"join-{verdict}", f"{frame.chain} run {frame.run} seq {frame.seq}")
        return self.ready(hosted, plan, speed, wall)

    def ready(self, hosted: HostedStage, plan: PlanUpdate | None, speed: float, wall: float) -> Iterator[ChainFrame]:
        """The steps of a running fan-in stage whose inputs are all in or whose wait is over, as the
        inputs its gate releases, in order. The caller runs each before it takes the next (a step's
        seq is the gate's next after the runs before it), and takes them all."""
        component = hosted.component
        if hosted.lifecycle is not Lifecycle.RUNNING or not isinstance(component, JoinedComponent):
            return
        running = self.running(plan)
        expected = {name for name in component.join.flows if name in running}
        wait = join_wait_s(hosted.chain.period_s, speed)
        before = component.join.missing
        for join in component.join.ready(expected, wall, wait):
            if join.lost:  # an input of a producer that had delivered before: lost or late
                self._count("join-missing", f"{hosted.stage.name} step {join.step} ran without "
                            f"{', '.join(join.lost)}", logging.INFO)
            elif join.missing:  # at start-up: a producer that has not produced anything yet
                self._tally("join-not-started", len(join.missing))
            seq = hosted.gate.next_seq if hosted.gate.next_seq is not None else 0
            frame = ChainFrame(chain=hosted.chain.name, run=hosted.run, seq=seq, target=hosted.index,
                               t_virtual=join.step * hosted.chain.period_s, t_unix=join.t_unix,
                               payload_len=len(join.payload), payload=join.payload)
            self._joined(frame.chain, frame.run, seq)
            yield from hosted.gate.offer(seq, frame, now=wall)
        if component.join.missing != before:
            self._tally("join-missing-inputs", component.join.missing - before)

    def consumed(self, hosted: Iterable[HostedStage]) -> dict[str, Consumed]:
        """Each running fan-in stage's edge gates, as acknowledgements to the flows' producers."""
        out = {}
        for stage in hosted:
            if stage.lifecycle is Lifecycle.RUNNING and isinstance(stage.component, JoinedComponent):
                out.update(stage.component.join.consumed(stage.generation))
        return out

    def producers(self, hosted: Iterable[HostedStage], plan: PlanUpdate | None) -> dict[str, str | None]:
        """Per flow into a stage hosted here: where the plan runs its producer."""
        placement = plan.placement if plan else {}
        return {f.name: placement.get(f.producer) for h in hosted for f in self._in.get(h.stage.name, ())}

    @staticmethod
    def stats(hosted: Mapping[str, HostedStage]) -> dict[str, dict[str, int]]:
        """Per fan-in stage hosted here: steps joined, inputs late, missing, empty steps."""
        return {name: {"joined": h.component.join.joined, "late": h.component.join.late,
                       "missing": h.component.join.missing, "not_started": h.component.join.not_started,
                       "empty_steps": h.component.join.empty_steps}
                for name, h in hosted.items() if isinstance(h.component, JoinedComponent)}


__all__ = ["EdgeGate", "Flows", "JoinState", "JoinedComponent", "flow_chains", "join_wait_s", "ProtocolError"]
