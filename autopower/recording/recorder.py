"""The live side of a recording: a bus tap that turns protocol traffic into `Telemetry` calls.

Each process (agent, base station) wraps its bus once::

    recorder = open_recorder(run_dir, node, scenario=scenario)  # autopower.recording.live; or
                                                               # Recorder.open (no output drawings)
    bus = recorder.tap(ZenohBus(settings))   # a RecordingBus: same Bus surface -> runs/<run-id>/<node>.rrd
    ...
    recorder.attach(runtime)        # the sink's outputs (`NodeRuntime.listen`), see below
    bus.close()                     # closes the inner bus, flushes and closes the recording

Every process of a run writes its own file with the same recording id (derived from the run
directory's name, so nobody has to pass it around) and `merge_recordings` joins them into
``run.rrd`` with ``rerun rrd merge``.

What is recorded, on the mission timeline (virtual seconds; the clock comes from the first
`PlanUpdate` seen, or from `clock=`):

- own `NodeStatus` published (whole, or its `StatusDelta` made whole again) -> ``robots/<r>/battery_j``, ``robots/<r>/power_w/<part>`` (and
  ``total``), ``custody/<node>/resent|held|evicted`` (frames resent after a silent loss, kept
  until acknowledged, given up), ``robots/<r>/overhead_j/migration|recovery`` (cumulative energy outside the model's
  steady state, see `autopower.node.meter`), ``team/links/<a>-<b>/up`` when a neighbour's visibility changes, sink and source
  counters under ``components/<chain>/sink|source/...``, and the model's power for what the
  robot runs ``robots/<r>/model_w`` (`NodeStatus.model_w`, logged when it changes);
- `PlanUpdate` published -> ``team/allocation`` and ``team/network`` graphs and a decision text
  event (type ``plan``, with the policy, its reasons and its ``predicted_w``), at publication;
- a plan received -> this node's predicted battery line from its next status (the plan's
  ``predicted_w`` for it: ``predicted/<r>/battery_j`` and ``predicted/<r>/empty``, see
  `Telemetry.prediction`);
- `StageReady` published -> a migration text event with its downtime; control messages
  (``assign``, ``prepare``, ``migrate-out``, ``release``) and any other message a process
  publishes (relayed hops, subgroup rounds) -> ``events/messages`` (DEBUG), typed by KIND, kept
  out of the events timeline;
- own first status -> ``team/alive/<r>`` 1; liveliness lost / regained -> ``alive`` 0 / 1 (steps)
  and fault text events (phase ``detected`` / ``restored``);
- sink stats in a status -> ``components/<chain>/sink/received_total``, ``duplicates_total``,
  ``missing`` (seqs below the highest seen not arrived yet), ``latency_ms_p50|max`` (end to end);
- outputs reaching this node as their sink (`on_output`) -> ``components/<chain>/run/<run>/seq``;
  results its full hold let go (`SinkListener.held_dropped`) -> ``components/<chain>/run/<run>/held_dropped``,
  and those a latest-only chain's newer result replaced in it -> ``.../run/<run>/superseded``;
  outputs a restarted sink's journal says its crashed process delivered in its last commit
  (`SinkListener.sink_journal`: their recording may have died with it) -> ``.../run/<run>/sink_journal``
  (one scalar per output: replay checks exactly-once per (chain, run, seq)); at a clean stop
  (`record_stop`), what each source here produced per run -> ``.../run/<run>/produced`` and every
  frame still in hand -> ``.../run/<run>/in_flight`` (one scalar per seq); and, at most every
  `visual_every_s`, what the injected `visualise` draws (the deploy layer's draws a downscaled
  camera frame on ``components/<chain>/camera`` with the blobs as ``Boxes2D`` on ``.../blobs``,
  MCL particles and pose as ``Points2D`` on ``components/<chain>/particles`` and ``.../pose``
  over the map (static, ``.../map``); chains are single-stage, so <chain> is also the stage);
- `record_fault(...)` / `record_fault_event(run_dir, ...)` for tools that inject faults
  (``phase="injected"``): replay measures detection and reconfiguration from them.

Text events carry a machine-readable JSON tail after `EVENT_TAG` (see `tag_event`/
`parse_event`), so replay derives detection, reconfiguration and downtime without guessing.

Logging never stops a robot: every handler catches everything, `Telemetry` never raises, and
scalars and texts are batched with ``send_columns`` (flushed every `flush_every_s`).
Data still buffered when a process is SIGKILLed (≤ `flush_every_s`) is lost. Outputs follow the
sink's commits instead of that timer: an output is written to the recording only by `flush_outputs`,
which the process calls right after the sink notes what it took in (`node.sink_store`) and before
the status that acknowledges it leaves. An output taken in after the last commit
is then neither noted, nor acknowledged, nor recorded when the process dies: custody resends it and
the restarted sink records it once.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
import uuid
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Mapping

from autopower.errors import AutoPowerError, ProtocolError
from autopower.model.parts import OVERHEAD_KINDS, overhead_kind
from autopower.node.ports import SinkListener
from autopower.protocol.codec import decode, message_kind, wire_data
from autopower.protocol.messages import NodeStatus, StatusDelta
from autopower.protocol.plans import PlanAssembler
from autopower.protocol.statuses import StatusAssembler
from autopower.recording.telemetry import (
    EVENT_TAG,
    MESSAGES,
    Telemetry,
    alive_path,
    component_path,
    link_path,
)

log = logging.getLogger(__name__)


MERGED_NAME = "run.rrd"
# (rerun module, chain, seq, output bytes) -> [(sub-entity, archetype)] or (sub-entity, archetype,
# True) for static data (a map): how to draw a chain's output. Injected by the deploy layer
# (`autopower.recording.live`), which may import the chains.
Visualiser = Callable[[Any, str, int, bytes], list[tuple]]
_RUN_NAMESPACE = uuid.UUID("5d1f4b7e-7c55-4c1e-9a0e-6a2f0b1f3a11")


# ---------------------------------------------------------------------------------------------
# structured text events
# ---------------------------------------------------------------------------------------------


def tag_event(text: str, **payload: Any) -> str:
    """A text event line: human `text`, then `EVENT_TAG` and `payload` as compact JSON."""
    return f"{text}{EVENT_TAG}{json.dumps(payload, sort_keys=True, separators=(',', ':'), default=str)}"


def parse_event(line: str | None) -> tuple[str, dict[str, Any] | None]:
    """Split a text event into (human text, payload or None)."""
    if not line:
        return "", None
    text, tag, tail = line.rpartition(EVENT_TAG)
    if not tag:
        return line, None
    try:
        payload = json.loads(tail)
    except ValueError:
        return line, None
    return (text, payload) if isinstance(payload, dict) else (line, None)


def _peek(payload: bytes) -> tuple[str | None, dict]:
    """(kind, fields by name) of an AutoPower message: the tap reads what its own process has just
    encoded, through the strict codec (a status in about 25 µs, decoded and named). Anything odd
    raises `ProtocolError`, and the recorder's guard counts and drops it."""
    msg = decode(payload)
    return msg.KIND, wire_data(msg)


def _peek_items(payload: bytes) -> list[tuple[str | None, dict]]:
    """`_peek` of a message, or of each message of a `Batch` (a node's orders or answers in one put)."""
    kind, fields = _peek(payload)
    if kind != "batch":
        return [(kind, fields)]
    return [_peek(item) for item in fields["items"]]


def run_recording_id(run_dir: str | Path) -> str:
    """The recording id every process of the run in `run_dir` uses (from the folder's name)."""
    return str(uuid.uuid5(_RUN_NAMESPACE, Path(run_dir).resolve().name))


def output_path(chain: str, run: int) -> str:
    """Entity of a chain's outputs at its sink in one run: one scalar (the seq) per output."""
    return f"{component_path(chain, f'run/{int(run)}')}/seq"


def held_dropped_path(chain: str, run: int) -> str:
    """Entity of a chain's results dropped in one run by a robot's full hold: one scalar (the seq) each."""
    return f"{component_path(chain, f'run/{int(run)}')}/held_dropped"


def superseded_path(chain: str, run: int) -> str:
    """Entity of a latest-only chain's results a robot let go from its hold in one run, each replaced
    by a newer one: one scalar (the seq) each."""
    return f"{component_path(chain, f'run/{int(run)}')}/superseded"


def died_with_process_path(chain: str, run: int) -> str:
    """Entity of a chain's outputs that died with a crashed process of their robot (source and sink
    there, the frame in its memory only): one scalar (the seq) each, logged by the restarted process."""
    return f"{component_path(chain, f'run/{int(run)}')}/died_with_process"


def sink_journal_path(chain: str, run: int) -> str:
    """Entity of a chain's outputs that a restarted sink's journal says the crashed process delivered
    in its last commit (`SinkStore.last_batch`): one scalar (the seq) each."""
    return f"{component_path(chain, f'run/{int(run)}')}/sink_journal"


def produced_path(chain: str, run: int) -> str:
    """Entity of how many outputs a chain's source produced in one run (seqs 0 .. n-1), logged by
    the source's node as it stops (`Recorder.record_stop`)."""
    return f"{component_path(chain, f'run/{int(run)}')}/produced"


def in_flight_path(chain: str, run: int) -> str:
    """Entity of a chain's frames a node still had in hand as it stopped (`NodeRuntime.in_flight_at_stop`):
    one scalar (the seq) each."""
    return f"{component_path(chain, f'run/{int(run)}')}/in_flight"


def record_fault(telemetry: Telemetry, t_s: float, *, kind: str, target: str, phase: str = "injected",
                 reason: str = "", observer: str | None = None) -> None:
    """Log a fault event replay understands: `kind` (``cut``, ``kill``, ``freeze``, ``radio``,
    ``node-lost``...), `target` (``r1-laptop`` or ``r2``), `phase` (``injected``, ``detected``,
    ``healed``, ``restored``)."""
    human = f"{kind} {target} {phase}" + (f": {reason}" if reason else "")
    telemetry.fault(t_s, tag_event(human, type="fault", kind=kind, target=target, phase=phase,
                                   reason=reason, observer=observer))


def record_fault_event(run_dir: str | Path, *, kind: str, target: str, phase: str = "injected", reason: str = "",
                       mission: Mapping[str, Any] | None = None, t_s: float | None = None,
                       wall_unix: float | None = None) -> Path:
    """For a one-shot tool (``autopower fault cut r1 laptop``): write one fault event into its own
    ``<run_dir>/fault-<n>.rrd`` of the run's recording (merged with the others at the end).

    Mission time is `t_s`, or derived from `mission` (the coordinator snapshot's ``"mission"``:
    ``epoch_unix`` and ``speed``) at `wall_unix` (default now).
    """
    if t_s is None:
        if mission is None:
            raise AutoPowerError("record_fault_event needs t_s or the mission (epoch_unix, speed) to place "
                                 "the fault on the mission timeline")
        wall = time.time() if wall_unix is None else wall_unix
        t_s = max(0.0, (wall - float(mission["epoch_unix"])) * float(mission["speed"]))
    run_dir = Path(run_dir)
    path = run_dir / f"fault-{time.time_ns()}-{os.getpid()}.rrd"
    with Telemetry(path, recording_id=run_recording_id(run_dir), kind="live",
                   properties={"node": "fault-tool", "run": run_dir.resolve().name}) as telemetry:
        record_fault(telemetry, t_s, kind=kind, target=target, phase=phase, reason=reason, observer="fault-tool")
    return path


# ---------------------------------------------------------------------------------------------
# the recorder
# ---------------------------------------------------------------------------------------------


def _fresh_path(run_dir: Path, node: str) -> Path:
    """``<node>.rrd``, or ``<node>.restart-<n>.rrd`` for a process started again after a crash
    (its earlier file is kept: the merge joins every file of the run)."""
    path = run_dir / f"{node}.rrd"
    n = 0
    while path.exists():
        n += 1
        path = run_dir / f"{node}.restart-{n}.rrd"
    return path


class Recorder:
    """Turns one process's protocol traffic into Telemetry calls; thread-safe, never raises."""

    def __init__(self, telemetry: Telemetry, node: str, *, team: str | None = None,
                 clock: Callable[[], float] | None = None, flush_every_s: float = 1.0,
                 visual_every_s: float = 0.5, owns_telemetry: bool = True,
                 visualise: Visualiser | None = None, quality=None):
        self.telemetry = telemetry
        self.node = node
        self.keys = None
        if team is not None:
            from autopower.protocol import Keys

            self.keys = Keys(team)
        self._clock = clock
        self._mission = None  # MissionInfo from the first PlanUpdate
        # new plans come as their change from the one before. What this process publishes and
        # what it receives are two streams, each assembled on its own: a base station hears its
        # own plans back, and one assembler taking the change first on the way in had nothing
        # left to apply on the way out (the decision of that epoch went unrecorded)
        self._plans = {"publish": PlanAssembler(), "receive": PlanAssembler()}
        self._statuses = StatusAssembler()  # its own statuses, whole again (each is sent as its change from a whole one)
        self._runtime = None  # the NodeRuntime `attach` records the outputs of
        self._lock = threading.RLock()
        self.flush_every_s = flush_every_s
        self.visual_every_s = visual_every_s
        self._last_flush = time.monotonic()
        # outputs taken in since the sink's last commit, (entity, mission t, seq) each: written only
        # with the commit (`flush_outputs`). The timed flush must not write them: an output recorded
        # but not noted is delivered again by a restarted sink when custody resends it
        self._outputs_held: list[tuple[str, float, int]] = []
        self._last_visual: dict[str, float] = {}
        self._last_epoch = -1
        self._links_seen: dict[str, bool] = {}
        self._epochs_seen: dict[str, int] = {}
        self._all_links: dict[frozenset, SimpleNamespace] = {}
        self._lost: set[str] = set()
        self._alive: set[str] = set()
        self._predicted: tuple[int, float] | None = None  # (plan epoch, this node's predicted W) to log
        self._predicted_epoch = -1
        self._model_w: dict[str, float] = {}  # robot -> the model power last logged for it
        self._down: dict[str, tuple] = {}  # robot -> the downtime last logged for it (NodeStatus.down)
        self._flow_consumed: dict[str, int] = {}  # entity path -> the next_seq last logged (`_ack`)
        self._owns = owns_telemetry
        self.visualise = visualise
        # (chain, seq, output, variants) -> metrics against the ground truth (`recording.live.QualityScorer`)
        self.quality = quality
        self._variants: dict[str, str] = {}  # the quality variants the plans run
        self.errors = 0
        self.closed = False

    @classmethod
    def open(cls, run_dir: str | Path, node: str, *, recording_id: str | None = None, scenario=None,
             kind: str = "live", properties: dict | None = None, **kwargs) -> "Recorder":
        """A recorder writing ``<run_dir>/<node>.rrd`` with the run's recording id."""
        run_dir = Path(run_dir)
        props = {"node": node, "run": run_dir.resolve().name}
        if scenario is not None:
            props.update(scenario=scenario.name, accounting=scenario.accounting,
                         topology=scenario.network_spec.topology, basestation=scenario.basestation)
        props.update(properties or {})
        telemetry = Telemetry(_fresh_path(run_dir, node), recording_id=recording_id or run_recording_id(run_dir),
                              kind=kind, properties=props, flush_rows=20_000)
        return cls(telemetry, node, **kwargs)

    def tap(self, bus) -> "RecordingBus":
        """Wrap `bus`: what goes through it is recorded; closing it closes both."""
        return RecordingBus(bus, self)

    def attach(self, runtime) -> None:
        """Record every output reaching `runtime` (a `NodeRuntime`) as its chain's sink, and every
        result its full hold lets go."""
        runtime.listen(SinkListener(output=self.on_output, held_dropped=self.on_held_dropped,
                                    died_with_process=self.on_died_with_process,
                                    sink_journal=self.on_sink_journal))
        # the mission clock of a runtime that started without a plan on the bus (a robot restarted
        # out of the base station's reach goes on with its saved plan): its outputs were logged at 0
        self._runtime = runtime

    # ---- time --------------------------------------------------------------------------------------
    def now(self) -> float:
        """Mission time (virtual seconds); 0 until the mission clock is known."""
        if self._clock is not None:
            return float(self._clock())
        m = self._mission
        if m is None:
            clock = getattr(self._runtime, "clock", None)
            return max(0.0, float(clock.now())) if clock is not None else 0.0
        return max(0.0, (time.time() - m.epoch_unix) * m.speed)

    # ---- entry points (called from the bus wrapper; each catches everything) -------------------------
    def _guard(self, what: str, fn: Callable, *args) -> None:
        try:
            with self._lock:
                if not self.closed:
                    fn(*args)
                    self._maybe_flush()
        except Exception as exc:  # noqa: BLE001 - recording must never stop a robot
            self.errors += 1
            if self.errors <= 3:
                log.warning("recorder %s: %s failed (%s: %s); continuing", self.node, what,
                            type(exc).__name__, exc)

    def _keys(self, key: str):
        if self.keys is None:
            from autopower.protocol import Keys

            parts = key.split("/")
            if len(parts) < 3:
                return None
            self.keys = Keys(parts[1])
        return self.keys

    def on_publish(self, key: str, payload: bytes) -> None:
        """What this process sends: its status, plans, stage-ready notices."""
        if key.endswith("/data"):  # the data plane: by far the most traffic, nothing to record
            return
        self._guard("publish", self._published, key, payload)

    def _published(self, key: str, payload: bytes) -> None:
        keys = self._keys(key)
        if keys is None:
            return
        if keys.node_of_status(key) is not None:
            # each one it sends passes here, its keyframes first: every change applies
            status = self._statuses.whole(decode(payload, (NodeStatus, StatusDelta)))
            if status is not None:
                self._status(wire_data(status))
        elif keys.node_of_peer(key) is not None:
            return  # the part of the status just logged that robots read (`PeerStatus`)
        elif keys.addressed_ends(key) is not None:
            kind, fields = _peek(payload)
            if kind == "ack":
                self._ack(fields)
        elif key == keys.plan:
            fields = self._whole_plan(payload, "publish")
            if fields is not None:
                self._plan(fields)
        elif key == keys.inbox:
            for kind, fields in _peek_items(payload):
                if kind == "stage-ready":
                    self._stage_ready(fields)
                elif kind == "stage-failed":
                    self._stage_failed(fields)
        else:  # control messages and whatever else a process announces (e.g. subgroup rounds)
            for kind, fields in _peek_items(payload):
                self._other(key, kind, fields)

    def on_receive(self, key: str, payload: bytes) -> None:
        """What this process receives: only plans matter (the mission clock, this node's predicted
        power), on the plan key or on this node's control key (a robot's plans, whole or as changes)."""
        if not (key.endswith("/base/plan") or key.endswith(f"/node/{self.node}/control")):
            return
        self._guard("receive", self._received_plan, key, payload)

    def _whole_plan(self, payload: bytes, stream: str) -> dict | None:
        """The fields of the whole plan ``payload`` carries or makes (a new plan goes out as its
        change from the one before, `protocol.plans`); None for anything else."""
        kind = message_kind(payload)  # the header only: a control key carries migrations' state too
        if kind is None:
            raise ProtocolError("not an AutoPower message")
        if kind not in ("plan", "plan-change"):
            return None
        plan = self._plans[stream].whole(payload)
        if plan is None:
            return None
        return wire_data(plan)

    def _received_plan(self, key: str, payload: bytes) -> None:
        fields = self._whole_plan(payload, "receive")
        if fields is None:
            return
        if self._mission is None:
            self._set_mission(fields["mission"])
        epoch, watts = int(fields["epoch"]), (fields.get("predicted_w") or {}).get(self.node)
        if watts is not None and epoch > self._predicted_epoch:
            # drawn from this node's next status, which has the battery to start the line from
            self._predicted_epoch = epoch
            self._predicted = (epoch, float(watts))

    def _set_mission(self, mission: dict) -> None:
        self._mission = SimpleNamespace(epoch_unix=float(mission["epoch_unix"]), speed=float(mission["speed"]),
                                        accounting=mission.get("accounting"),
                                        energies_j=dict(mission.get("energies_j") or {}))

    def on_liveliness(self, key: str, alive: bool) -> None:
        self._guard("liveliness", self._liveliness, key, alive)

    def on_output(self, chain: str, run: int, seq: int, data: bytes) -> None:
        """An output reached this node, its chain's sink (its `SinkListener.output`)."""
        self._guard("output", self._output, chain, run, seq, data)

    def on_held_dropped(self, chain: str, run: int, seq: int, why: str = "budget") -> None:
        """A result this node held for a sink out of its reach was let go (hook for
        `SinkListener.held_dropped`): its hold budget full, or superseded by a newer result of a
        latest-only chain; the replay counts each apart (a superseded one only with a later one delivered)."""
        path = superseded_path(chain, run) if why == "superseded" else held_dropped_path(chain, run)
        self._guard("held-dropped", lambda: self.telemetry.scalar(path, self.now(), seq))

    def on_sink_journal(self, chain: str, run: int, seq: int) -> None:
        """An output the crashed sink here had delivered and noted in its last commit (hook for
        `SinkListener.sink_journal`, called by the restarted one): the replay takes it as delivered."""
        self._guard("sink-journal", lambda: self.telemetry.scalar(sink_journal_path(chain, run), self.now(), seq))

    def on_died_with_process(self, chain: str, run: int, seq: int) -> None:
        """An output of this robot's chains that died with its crashed process (hook for
        `SinkListener.died_with_process`, called by the restarted one): the replay counts it apart."""
        self._guard("died-with-process",
                    lambda: self.telemetry.scalar(died_with_process_path(chain, run), self.now(), seq))

    def record_stop(self, runtime) -> None:
        """At a clean stop (the process's loop has ended): what each source here produced in each
        run, and every frame this node still had in hand. The replay bounds each chain's tail with
        the first and checks every output it calls in flight against the second."""
        self._guard("stop", self._stop, runtime)

    def _stop(self, runtime) -> None:
        t = self.now()
        for (chain, run), produced in sorted(runtime.feeds.produced_by_run.counts().items()):
            self.telemetry.scalar(produced_path(chain, run), t, produced)
        for (chain, run), seqs in sorted(runtime.in_flight_at_stop().items()):
            path = in_flight_path(chain, run)
            for seq in sorted(seqs):
                self.telemetry.scalar(path, t, seq)

    def fault(self, *, kind: str, target: str, phase: str = "injected", reason: str = "") -> None:
        with self._lock:
            record_fault(self.telemetry, self.now(), kind=kind, target=target, phase=phase, reason=reason,
                         observer=self.node)

    # ---- handlers ----------------------------------------------------------------------------------------
    def _status(self, s: dict) -> None:
        tel, t, node = self.telemetry, float(s["t_virtual"]), s["node"]
        if node not in self._alive:
            self._alive.add(node)
            tel.scalar(alive_path(node), t, 1.0)
        if s.get("battery_j") is not None:
            tel.battery(t, node, s["battery_j"])
            if self._predicted is not None:
                tel.prediction(t, node, s["battery_j"], self._predicted[1])
                self._predicted = None
            parts = dict(s.get("power_w") or {})
            parts.setdefault("total", sum(parts.values()))
            tel.power(t, node, parts)
            overhead = {kind: 0.0 for kind in OVERHEAD_KINDS}
            for name, joules in (s.get("energy_j") or {}).items():
                kind = overhead_kind(name)
                if kind is not None:
                    overhead[kind] += float(joules)
            for kind, joules in overhead.items():
                tel.scalar(f"robots/{node}/overhead_j/{kind}", t, joules)
            # the bytes on its links since its process started (a restart counts from 0 again)
            for what, pair in (("link", s.get("link_bytes")), ("control", s.get("control_bytes"))):
                if pair:
                    tel.scalar(f"robots/{node}/bytes/{what}_sent", t, float(pair[0]))
                    tel.scalar(f"robots/{node}/bytes/{what}_received", t, float(pair[1]))
            # CPU seconds on the computer running it since its process took the mission up: the
            # runtime's own (charged as `cpu_runtime`) and the component code's
            for what in ("runtime", "component"):
                if s.get(f"{what}_cpu_s") is not None:
                    tel.scalar(f"robots/{node}/cpu_s/{what}", t, float(s[f"{what}_cpu_s"]))
            # the model's power for what the robot runs, by its own account: a plan names a robot
            # it cannot reach, a subgroup's placement is not the base station's, a stage runs on
            # until its migration lands; the robot knows which plan it runs
            down = s.get("down")
            if down is not None and self._down.get(node) != tuple(down):
                # restarted: while it was down the robot drew what its meter charges for that time
                self._down[node] = tuple(down)
                self._model_w[node] = float(down[1])
                tel.scalar(f"robots/{node}/model_w", float(down[0]), float(down[1]))
            model_w = s.get("model_w")
            if model_w is not None and self._model_w.get(node) != model_w:
                self._model_w[node] = model_w
                tel.scalar(f"robots/{node}/model_w", t, float(model_w))
        if s.get("plan_epoch") is not None and self._epochs_seen.get(node) != s["plan_epoch"]:
            # when each robot runs a plan: replay's "reconfigured" is when every robot runs it
            self._epochs_seen[node] = s["plan_epoch"]
            tel.scalar(f"robots/{node}/plan_epoch", t, float(s["plan_epoch"]))
        for peer, up in (s.get("links") or {}).items():
            path = link_path(node, peer)
            if self._links_seen.get(path) != up:
                self._links_seen[path] = up
                tel.scalar(f"{path}/up", t, 1.0 if up else 0.0)
        for chain, st in (s.get("sinks") or {}).items():
            tel.scalar(component_path(chain, "sink/received_total"), t, st["received_total"])
            tel.scalar(component_path(chain, "sink/duplicates_total"), t, st["duplicates_total"])
            # seqs of the current run below the highest seen that have not arrived (yet)
            tel.scalar(component_path(chain, "sink/missing"), t, max(0, int(st["max_seq"]) + 1 - int(st["received"])))
            if st["received"]:
                tel.scalar(component_path(chain, "sink/latency_ms_p50"), t, st["latency_ms_p50"])
                tel.scalar(component_path(chain, "sink/latency_ms_max"), t, st["latency_ms_max"])
        for chain, st in (s.get("sources") or {}).items():
            tel.scalar(component_path(chain, "source/produced_total"), t, st["produced_total"])
        counters = s.get("counters") or {}
        for name, what in (("custody-resent", "resent"), ("custody-frames", "held"), ("custody-evicted", "evicted"),
                           ("held-outputs-dropped", "held_dropped"), ("held-outputs-superseded", "superseded")):
            # frames lost in flight and resent (see autopower.node.custody); results a robot cut off
            # from their sink dropped beyond the hold budget (`[delivery] hold_budget_mb`)
            if name in counters:
                tel.scalar(f"custody/{node}/{what}", t, counters[name])

    def _ack(self, a: dict) -> None:
        """What this node consumed, as sent to a producer: each DAG flow's edge gate ("P>C#0")."""
        t = self.now()
        for key, c in (a.get("consumed") or {}).items():
            producer, sep, consumer = key.rpartition("#")[0].partition(">")
            if sep and isinstance(c, dict) and "next_seq" in c:
                path = component_path(consumer, f"inputs/{producer}/consumed")
                if self._flow_consumed.get(path) != c["next_seq"]:  # sent to each producer: logged once
                    self._flow_consumed[path] = c["next_seq"]
                    self.telemetry.scalar(path, t, c["next_seq"])

    def _plan(self, p: dict) -> None:
        self._set_mission(p["mission"])
        epoch = int(p["epoch"])
        if epoch <= self._last_epoch:
            return
        self._last_epoch = epoch
        self._variants = dict(p.get("variants") or {})
        # when it was published (plan_t_virtual is the start of the prediction's baseline, which
        # a plan that only drops a robot keeps)
        tel, t = self.telemetry, self.now()
        placement, links = dict(p["placement"]), [(l["a"], l["b"], l["medium"]) for l in p["links"]]
        nodes = sorted({*placement.values(), *(x for a, b, _ in links for x in (a, b))})
        tel.allocation(t, placement, nodes)
        for a, b, _ in links:
            self._all_links[frozenset((a, b))] = SimpleNamespace(a=a, b=b)
        network = SimpleNamespace(nodes=nodes, links=[SimpleNamespace(a=a, b=b, medium=m) for a, b, m in links])
        tel.network(t, network, list(self._all_links.values()))
        predicted = dict(p.get("predicted_w") or {})
        life = p.get("predicted_lifetime_s")
        reasons = [str(r) for r in p.get("reasons") or ()]
        human = (f"plan epoch {epoch}: " + ", ".join(f"{s} → {h}" for s, h in sorted(placement.items()))
                 + (f"; predicted lifetime {life:,.0f} s" if life is not None else "")
                 + (f" ({p['policy']}: {'; '.join(reasons)})" if reasons and p.get("policy") else ""))
        tel.decision(t, tag_event(human, type="plan", epoch=epoch, placement=placement, policy=p.get("policy") or None,
                                  reasons=reasons,
                                  running=dict(p.get("running") or {}), predicted_w=predicted,
                                  predicted_lifetime_s=life, accounting=self._mission.accounting,
                                  speed=self._mission.speed, epoch_unix=self._mission.epoch_unix,
                                  links=[list(l) for l in links], energies_j=self._mission.energies_j,
                                  by=self.node, variants=dict(self._variants),
                                  levels=dict(p.get("levels") or {})))

    def _stage_ready(self, m: dict) -> None:
        moved = "state imported" if m["imported_state"] else "fresh start"
        human = (f"{m['stage']} runs on {m['node']} (generation {m['generation']}, {moved}, downtime "
                 f"{m['downtime_ms']:.1f} ms, {m['buffered']} input(s) buffered)")
        self.telemetry.migration(self.now(), tag_event(
            human, type="stage-ready", stage=m["stage"], node=m["node"], generation=m["generation"],
            imported_state=m["imported_state"], downtime_ms=m["downtime_ms"], buffered=m["buffered"],
            resume_seq=m.get("resume_seq")))

    def _stage_failed(self, m: dict) -> None:
        after = "it keeps running there" if m["running"] else "stopped"
        human = f"{m['stage']} failed on {m['node']} ({m['what']}: {m['detail']}); {after}"
        self.telemetry.migration(self.now(), tag_event(
            human, type="stage-failed", stage=m["stage"], node=m["node"], generation=m["generation"],
            what=m["what"], detail=m["detail"], running=m["running"]))

    def _other(self, key: str, kind: str | None, fields: dict) -> None:
        brief = {k: v for k, v in fields.items() if not isinstance(v, (bytes, bytearray))
                 and len(json.dumps(v, default=str)) <= 400}
        control = key.endswith("/control")
        target = key.rsplit("/", 2)[-2] if control else key
        human = f"{self.node} → {target}: {kind} " + ", ".join(f"{k}={v}" for k, v in brief.items()
                                                               if isinstance(v, (str, int, float)))
        # protocol chatter (control steps, relayed hops, subgroup rounds): its own entity, off the events view
        self.telemetry.text(MESSAGES, self.now(), tag_event(human.strip(), type=str(kind), key=key, by=self.node,
                                                          **{k: v for k, v in brief.items()
                                                             if k not in ("type", "key", "by")}), "DEBUG")

    def _liveliness(self, key: str, alive: bool) -> None:
        keys = self._keys(key)
        node = keys.node_of_alive(key) if keys is not None else None
        if node is None or node == self.node:
            return
        if not alive and node not in self._lost:
            self._lost.add(node)
            self.telemetry.scalar(alive_path(node), self.now(), 0.0)
            record_fault(self.telemetry, self.now(), kind="node-lost", target=node, phase="detected",
                         reason=f"{self.node} lost {node}'s liveliness", observer=self.node)
        elif alive and node in self._lost:
            self._lost.discard(node)
            self.telemetry.scalar(alive_path(node), self.now(), 1.0)
            record_fault(self.telemetry, self.now(), kind="node-lost", target=node, phase="restored",
                         reason=f"{self.node} sees {node} again", observer=self.node)

    def _output(self, chain: str, run: int, seq: int, data: bytes) -> None:
        t = self.now()
        self._outputs_held.append((output_path(chain, run), t, seq))
        if self.quality is not None:  # measured quality: beside the declared score
            for metric, value in self.quality(chain, seq, data, self._variants).items():
                self.telemetry.scalar(component_path(chain, f"quality/{metric}"), t, float(value))
        last = self._last_visual.get(chain)
        wall = time.monotonic()
        if last is not None and wall - last < self.visual_every_s:
            return
        self._last_visual[chain] = wall
        self._visual(chain, t, seq, data)

    def _visual(self, chain: str, t: float, seq: int, data: bytes) -> None:
        if self.visualise is None or self.telemetry.rr is None:
            return
        for what, archetype, *static in self.visualise(self.telemetry.rr, chain, seq, data):
            self.telemetry.log(component_path(chain, what), None if static and static[0] else t, archetype)

    # ---- flushing ------------------------------------------------------------------------------------------
    def _maybe_flush(self) -> None:
        now = time.monotonic()
        if now - self._last_flush >= self.flush_every_s:
            self._last_flush = now
            self.telemetry.flush()

    def flush(self) -> None:
        """Write out everything, the outputs taken in since the last commit included."""
        with self._lock:
            self._write_held_outputs()
            self.telemetry.flush()
            self._last_flush = time.monotonic()

    def _write_held_outputs(self) -> None:
        held, self._outputs_held = self._outputs_held, []
        for entity, t, seq in held:
            self.telemetry.scalar(entity, t, seq)

    def flush_outputs(self) -> None:
        """Write out the outputs taken in since the last commit (nothing if none): called right after
        the sink notes them (`node.sink_store`) and before anything acknowledges them. Only there: a
        publish of another node's status or acknowledgement (relayed) must not write outputs the sink
        has not noted."""
        if self._outputs_held:
            try:
                self.flush()
            except Exception as exc:  # noqa: BLE001 - recording must never stop a robot
                self.errors += 1
                log.warning("recorder %s: flush before acknowledging failed (%s); continuing", self.node, exc)

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._write_held_outputs()  # a clean stop: what the sink took in last is delivered
            if self._owns:
                self.telemetry.close()
            else:
                self.telemetry.flush()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RecordingBus:
    """A `Bus` that records what passes through it (see `Recorder`) and otherwise delegates."""

    def __init__(self, inner, recorder: Recorder):
        self.inner = inner
        self.recorder = recorder

    def __enter__(self) -> "RecordingBus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def on_output(self, chain: str, run: int, seq: int, data: bytes) -> None:
        self.recorder.on_output(chain, run, seq, data)

    @property
    def zid(self) -> str:
        return self.inner.zid

    def links(self) -> dict[str, list[tuple[str, str]]]:
        return self.inner.links()

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        self.inner.publish(key, payload, reliable=reliable)
        self.recorder.on_publish(key, payload)

    def subscribe(self, key_expr: str, callback):
        rec = self.recorder

        def tapped(key: str, payload: bytes) -> None:
            rec.on_receive(key, payload)
            callback(key, payload)

        return self.inner.subscribe(key_expr, tapped)

    def declare_token(self, key: str):
        return self.inner.declare_token(key)

    def watch_liveliness(self, key_expr: str, callback):
        rec = self.recorder

        def tapped(key: str, alive: bool) -> None:
            rec.on_liveliness(key, alive)
            callback(key, alive)

        return self.inner.watch_liveliness(key_expr, tapped)

    def serve(self, key: str, callback):
        return self.inner.serve(key, callback)

    def query(self, key: str, payload: bytes, timeout_s: float = 2.0) -> list[bytes]:
        return self.inner.query(key, payload, timeout_s)

    def repeat_until_next(self, key: str, payload: bytes, after_s: float, every_s: float) -> None:
        self.inner.repeat_until_next(key, payload, after_s, every_s)  # a copy: recorded once, when first put

    def flush_recording(self) -> None:
        """The outputs taken in since the sink's last commit written out: each process calls it
        right after `NodeRuntime.commit_sinks` and before its status and acknowledgements leave, so
        that each commit is flushed before the next (`node.sink_store`: only the last commit may
        miss its recording after a kill) and nothing is recorded that the sink has not noted."""
        self.recorder.flush_outputs()

    @property
    def repeated(self) -> int:
        return self.inner.repeated

    def close(self) -> None:
        try:
            self.inner.close()
        finally:
            self.recorder.close()


# ---------------------------------------------------------------------------------------------
# merging
# ---------------------------------------------------------------------------------------------




__all__ = ["EVENT_TAG", "MERGED_NAME", "Recorder", "RecordingBus", "output_path", "parse_event", "record_fault",
           "record_fault_event", "run_recording_id", "tag_event"]
