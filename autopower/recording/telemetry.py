"""Rerun telemetry shared by the simulator and the live runtime: one layout, one writer.

Logging can fail; the robot must not. Every `Telemetry` method catches its own errors, logs a
warning (once per kind of failure) and carries on; ``errors`` counts what was lost. ``rerun`` is
imported only when a `Telemetry` is opened (it costs ~80 MB of RSS).

Layout (timeline ``mission_time``: virtual mission seconds, a duration):

=================================  ==========================  ===========================================
entity path                        archetype                   what
=================================  ==========================  ===========================================
``robots/<robot>/battery_j``       Scalars                     remaining battery (J)
``robots/<robot>/power_w/total``   Scalars                     total power draw (W)
``robots/<robot>/power_w/<part>``  Scalars                     by part: ``cpu_idle``, ``cpu_busy``,
                                                               ``cpu_recovery``, ``cpu_backlog``,
                                                               ``cpu_runtime``,
                                                               ``<medium>/send``, ``/receive``, ``/sleep``,
                                                               ``/migration``, ``/recovery``, ``/control``
                                                               (a live status's ``802.11a:send`` maps to
                                                               ``802.11a/send``)
``team/allocation``                GraphNodes + GraphEdges     nodes and stages; a directed edge
                                                               stage → host, logged at every change
``team/network``                   GraphNodes + GraphEdges     the links in use (undirected)
``predicted/<robot>/battery_j``    Scalars                     the model's predicted battery line: from each
                                                               prediction (plan, configuration change) on
``predicted/<robot>/empty``        Scalars (points at 0 J)     where each prediction runs the battery dry
``team/alive/<robot>``             Scalars (steps)             1 while the robot is seen, 0 once lost
``team/hosts/<stage>``             StateChange                 the node a stage runs on, at every change
``team/links/<a>-<b>/up``          Scalars (steps)             1 while the link exists, 0 while cut
``team/links/<a>-<b>/state``       StateChange                 the medium it uses, or ``down``
``team/links/<a>-<b>/medium``      TextLog                     the medium it uses, at every change
``events/faults``                  TextLog (WARN)              link cuts/heals, radio faults, chains on/off,
                                                               robots joining/leaving, energy offsets
``events/migrations``              TextLog (INFO)              each move: stage, hosts, bytes, joules,
                                                               missed periods
``events/decisions``               TextLog (INFO)              every policy decision's reasons
``events/readable/<kind>``         TextLog                     faults, decisions, migrations without the
                                                               JSON tail replay parses: the events view
``events/messages``                TextLog (DEBUG)             protocol chatter (control, relay, subgroup
                                                               rounds): kept off the events timeline
``components/<stage>/...``         see the recorder            component outputs (blobs on a downscaled
                                                               camera frame, MCL particles on the map)
=================================  ==========================  ===========================================

States (``.../up``, ``team/alive/...``) carry a static ``SeriesLines(interpolation_mode=StepAfter)``
so they plot as steps, and every series a static name (and colour per robot) the legend shows.
The view a recording opens on (its blueprint) is designed in `autopower.recording.blueprint`
from the `Layout` of what was logged; a writer given ``blueprint=`` sends it when it closes.

The recording's property ``autopower`` (``/__properties/autopower``) holds ``kind``
(``simulation`` | ``live``), ``layout`` (`LAYOUT_VERSION`) and whatever the writer was given
(scenario, policy, seed, ...), so a replay can tell an AutoPower run from a foreign file.

Scalars and text logs are buffered and sent with ``send_columns`` (one call per entity per
flush: ~1000x cheaper than one ``log`` per value); graphs are logged as they change. The live
runtime calls `flush` periodically; several processes with the same recording id can write
their own files and ``rerun rrd merge`` them.
"""

from __future__ import annotations

import logging
import math
import uuid
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from autopower.errors import RecordingError

log = logging.getLogger(__name__)

TIMELINE = "mission_time"
APPLICATION_ID = "autopower"
LAYOUT_VERSION = 1
PROPERTY = "autopower"
ALLOCATION = "team/allocation"
NETWORK = "team/network"
FAULTS = "events/faults"
MIGRATIONS = "events/migrations"
DECISIONS = "events/decisions"
MESSAGES = "events/messages"
READABLE = "events/readable"  # the same events without their machine-readable tail: what the view shows
EVENT_TAG = " ~ap"  # human text, then this tag, then one JSON object (see recorder.tag_event)
EVENTS = "events"
HOSTS = "team/hosts"
PREDICTED = "predicted"
ALIVE = "team/alive"
LINKS = "team/links"
# suffix of the links' 0/1 state series (and ALIVE's): plotted as steps, not ramps
STATE_SUFFIXES = ("/up",)


def _part(name: str) -> str:
    return name.replace(":", "/").strip("/")


def battery_path(robot: str) -> str:
    return f"robots/{robot}/battery_j"


def power_path(robot: str, part: str = "total") -> str:
    return f"robots/{robot}/power_w/{_part(part)}"


def link_path(a: str, b: str) -> str:
    a, b = sorted((a, b))
    return f"team/links/{a}-{b}"


def component_path(stage: str, what: str) -> str:
    return f"components/{stage}/{_part(what)}"


# predictions reach into the future: kept out of ``robots/`` (whose last sample ends the mission)
def predicted_path(robot: str) -> str:
    return f"{PREDICTED}/{robot}/battery_j"


def depletion_path(robot: str) -> str:
    return f"{PREDICTED}/{robot}/empty"


def alive_path(robot: str) -> str:
    # not under robots/: an observer logs a loss at its own time, which must not stretch the mission
    return f"{ALIVE}/{robot}"


def host_path(stage: str) -> str:
    return f"{HOSTS}/{stage}"


def link_state_path(a: str, b: str) -> str:
    return f"{link_path(a, b)}/state"


def robot_colour(robot: str) -> tuple[int, int, int]:
    """A colour per robot, the same in every process's file (from the name, not the order seen)."""
    digits = "".join(ch for ch in robot if ch.isdigit())
    index = int(digits) if digits else zlib.crc32(robot.encode())
    return _PALETTE[index % len(_PALETTE)]


_PALETTE = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
            (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))


def _lighter(colour: tuple[int, int, int]) -> tuple[int, int, int]:
    return tuple(int(c + (255 - c) * 0.5) for c in colour)


def series_style(rr, entity: str):
    """The static style of a scalar entity: legend name, colour per robot, steps for states."""
    parts = entity.split("/")
    if parts[0] == PREDICTED and len(parts) == 3:
        robot, colour = parts[1], robot_colour(parts[1])
        if parts[2] == "battery_j":
            return rr.SeriesLines(names=f"{robot} model's prediction", colors=[_lighter(colour)], widths=[1.5])
        return rr.SeriesPoints(names=f"{robot} predicted empty", colors=[colour], markers="cross",
                               marker_sizes=[6.0])
    if parts[0] == "robots" and len(parts) >= 3:
        robot, what = parts[1], "/".join(parts[2:])
        colour = robot_colour(robot)
        if what == "battery_j":
            return rr.SeriesLines(names=f"{robot} measured", colors=[colour], widths=[2.0])
        if what.startswith("power_w/"):
            part = what[len("power_w/"):]
            return rr.SeriesLines(names="total" if part == "total" else _PART_NAMES.get(part, part.replace("/", " ")),
                                  widths=[2.0 if part == "total" else 1.0])
        if what == "model_w":
            return rr.SeriesLines(names=f"{robot} model", colors=[_lighter(colour)])
        return None
    if parts[0:2] == ALIVE.split("/") and len(parts) == 3:
        return rr.SeriesLines(names=f"{parts[2]} alive", colors=[robot_colour(parts[2])], **_STEPS)
    if entity.endswith(STATE_SUFFIXES):
        return rr.SeriesLines(names=f"{parts[-2]} up" if entity.endswith("/up") else parts[-2], **_STEPS)
    if parts[0] == "components" and len(parts) >= 4 and parts[2] in ("sink", "source"):
        return rr.SeriesLines(names=f"{parts[1]} {parts[3].replace('_total', '').replace('_', ' ')}")
    return None


# a state holds until the next change; zoomed out, a 0 and a 1 in one pixel must not average to 0.5
_STEPS = {"interpolation_mode": "StepAfter", "aggregation_policy": "Off"}
_PART_NAMES = {"cpu": "CPU", "cpu_idle": "CPU idle", "cpu_busy": "CPU busy (components)",
               "cpu_recovery": "CPU recovery", "cpu_backlog": "CPU backlog (a reconfiguration's)",
               "cpu_runtime": "CPU runtime (its own)"}


def new_recording_id() -> str:
    return str(uuid.uuid4())


@dataclass
class Layout:
    """What a recording holds, as far as a view of it needs: its entity paths and value ranges."""

    entities: set[str] = field(default_factory=set)
    battery_max_j: float = 0.0
    power_max_w: float = 0.0
    start_s: float = math.inf  # mission time span of the scalar series
    end_s: float = -math.inf

    def note(self, entity: str, values: Sequence[float] = (), times: Sequence[float] = ()) -> None:
        self.entities.add(entity)
        if times:
            self.start_s, self.end_s = min(self.start_s, min(times)), max(self.end_s, max(times))
        finite = [v for v in values if v is not None and math.isfinite(v)]
        if not finite:
            return
        if entity.endswith("/battery_j"):
            self.battery_max_j = max(self.battery_max_j, max(finite))
        elif entity.startswith("robots/") and "/power_w/" in entity:
            self.power_max_w = max(self.power_max_w, max(finite))

    def merge(self, other: "Layout") -> None:
        self.entities |= other.entities
        self.battery_max_j = max(self.battery_max_j, other.battery_max_j)
        self.power_max_w = max(self.power_max_w, other.power_max_w)
        self.start_s, self.end_s = min(self.start_s, other.start_s), max(self.end_s, other.end_s)

    def under(self, prefix: str) -> list[str]:
        """Entities at or below `prefix`, sorted."""
        return sorted(e for e in self.entities if e == prefix or e.startswith(prefix + "/"))

    def robots(self) -> list[str]:
        """Robots with a battery series."""
        return sorted({e.split("/")[1] for e in self.entities if e.startswith("robots/") and e.endswith("/battery_j")})

    def chains(self) -> list[str]:
        return sorted({e.split("/")[1] for e in self.entities if e.startswith("components/")})


class Telemetry:
    """A Rerun writer with the AutoPower layout that never raises into its caller.

    `blueprint` (a function of the `Layout` logged, e.g. `autopower.recording.blueprint.design`)
    is sent as the recording's default view when it closes; writers of one process of a run
    leave it out (the merge gives the run's file one view of everything).
    """

    def __init__(self, path: str | Path | None, *, recording_id: str | None = None, kind: str = "simulation",
                 properties: Mapping[str, Any] | None = None, flush_rows: int = 100_000, stream=None,
                 blueprint: Callable[[Layout], Any] | None = None):
        self.path = None if path is None else str(path)
        self.layout = Layout()
        self._blueprint = blueprint
        self._styled: set[str] = set()
        self._states: dict[str, tuple[list[float], list[str]]] = {}
        self._predictions: dict[str, tuple[float, float, float]] = {}
        self._hosts: dict[str, str] = {}
        self.recording_id = recording_id or new_recording_id()
        self.errors = 0
        self._warned: set[str] = set()
        self._scalars: dict[str, tuple[list[float], list[float]]] = {}
        self._texts: dict[str, tuple[list[float], list[str], list[str]]] = {}
        self._rows = 0
        self.flush_rows = flush_rows
        self._links: dict[str, tuple[bool, str | None]] = {}
        self.rr = None
        self.stream = None
        try:
            import rerun as rr

            self.rr = rr
            self.stream = stream or rr.RecordingStream(APPLICATION_ID, recording_id=self.recording_id)
            if self.path is not None:
                Path(self.path).parent.mkdir(parents=True, exist_ok=True)
                self.stream.save(self.path)
            values = {"kind": kind, "layout": LAYOUT_VERSION, "recording_id": self.recording_id,
                      **{k: v for k, v in dict(properties or {}).items() if v is not None}}
            self.stream.send_property(PROPERTY, rr.AnyValues(**{k: _property_value(v) for k, v in values.items()}))
        except Exception as exc:  # noqa: BLE001 - telemetry must never stop a robot or a simulation
            self._fail("open", exc)

    # ---- failure handling ------------------------------------------------------------------------
    def _fail(self, what: str, exc: BaseException) -> None:
        self.errors += 1
        if what not in self._warned:
            self._warned.add(what)
            log.warning("telemetry: %s failed (%s: %s); continuing without it", what, type(exc).__name__, exc)

    @property
    def enabled(self) -> bool:
        return self.stream is not None

    # ---- buffered series ---------------------------------------------------------------------------
    def scalar(self, entity: str, t_s: float, value: float) -> None:
        try:
            times, values = self._scalars.setdefault(entity, ([], []))
            times.append(float(t_s))
            values.append(float(value))
            self._count()
        except Exception as exc:  # noqa: BLE001
            self._fail("scalar", exc)

    def battery(self, t_s: float, robot: str, joules: float) -> None:
        self.scalar(battery_path(robot), t_s, joules)

    def power(self, t_s: float, robot: str, parts_w: Mapping[str, float]) -> None:
        """Power by part; include ``total``. Part names may use ``/`` or ``:`` (``802.11a:send``)."""
        for part, watts in parts_w.items():
            self.scalar(power_path(robot, part), t_s, watts)

    def text(self, entity: str, t_s: float, text: str, level: str = "INFO") -> None:
        try:
            times, texts, levels = self._texts.setdefault(entity, ([], [], []))
            times.append(float(t_s))
            texts.append(str(text))
            levels.append(level)
            self._count()
            human, tag, _ = str(text).rpartition(EVENT_TAG)
            if tag and entity in (FAULTS, DECISIONS, MIGRATIONS):
                # a person reads the event without the JSON a replay parses
                self.text(f"{READABLE}/{entity.rpartition('/')[2]}", t_s, human, level)
        except Exception as exc:  # noqa: BLE001
            self._fail("text", exc)

    def state(self, entity: str, t_s: float, text: str) -> None:
        """A named state (a link's medium, a stage's host) from `t_s` on: a lane in a state timeline."""
        try:
            times, states = self._states.setdefault(entity, ([], []))
            times.append(float(t_s))
            states.append(str(text))
            self._count()
        except Exception as exc:  # noqa: BLE001
            self._fail("state", exc)

    def prediction(self, t_s: float, robot: str, joules: float, watts: float) -> None:
        """The model's prediction at `t_s`: `robot` has `joules` and draws `watts` from now on.

        Logs the predicted battery line (where the previous prediction had got to, then the new
        start) and the predicted empty point; a prediction the previous one already makes (same
        power, battery on its line) is skipped, so calling this at every sample is cheap.
        """
        try:
            t, joules, watts = float(t_s), max(float(joules), 0.0), float(watts)
            previous = self._predictions.get(robot)
            if previous is not None:
                t0, e0, w0 = previous
                on_line = e0 - w0 * (t - t0)
                if abs(w0 - watts) <= 1e-9 * max(1.0, abs(w0)) and abs(on_line - joules) <= 1e-6 * max(1.0, e0):
                    return
                self.scalar(predicted_path(robot), t, max(on_line, 0.0))
            self.scalar(predicted_path(robot), t, joules)
            if watts > 0:
                self.scalar(depletion_path(robot), t + joules / watts, 0.0)
            self._predictions[robot] = (t, joules, watts)
        except Exception as exc:  # noqa: BLE001
            self._fail("prediction", exc)

    def _end_predictions(self) -> None:
        """Draw each robot's last predicted line down to where it runs dry."""
        for robot, (t0, e0, w0) in self._predictions.items():
            if w0 > 0:
                self.scalar(predicted_path(robot), t0 + e0 / w0, 0.0)
        self._predictions = {}

    def fault(self, t_s: float, text: str) -> None:
        self.text(FAULTS, t_s, text, "WARN")

    def migration(self, t_s: float, text: str) -> None:
        self.text(MIGRATIONS, t_s, text, "INFO")

    def decision(self, t_s: float, text: str) -> None:
        self.text(DECISIONS, t_s, text, "INFO")

    def _count(self) -> None:
        self._rows += 1
        if self._rows >= self.flush_rows:
            self.flush()

    def log(self, entity: str, t_s: float | None, *archetypes) -> None:
        """Log archetypes (e.g. ``rr.Points2D``) now, at mission time `t_s` (None: static); never raises.

        For low-rate visual data (component outputs); numbers belong in `scalar` (batched).
        """
        if self.stream is None:
            return
        try:
            self.layout.note(entity)
            if t_s is None:
                self.stream.log(entity, *archetypes, static=True)
                return
            self.stream.set_time(TIMELINE, duration=float(t_s))
            self.stream.log(entity, *archetypes)
        except Exception as exc:  # noqa: BLE001
            self._fail("log", exc)

    # ---- graphs (logged as they change) ----------------------------------------------------------
    def allocation(self, t_s: float, allocation: Mapping[str, str], nodes: Sequence[str]) -> None:
        """The placement as a graph: the team's nodes, every stage, an edge stage → host."""
        if self.stream is None:
            return
        try:
            rr = self.rr
            stages = sorted(allocation)
            ids = list(nodes) + [s for s in stages if s not in nodes]
            self.stream.set_time(TIMELINE, duration=float(t_s))
            self.stream.log(ALLOCATION, rr.GraphNodes(node_ids=ids, labels=ids),
                            rr.GraphEdges(edges=[(s, allocation[s]) for s in stages], graph_type="directed"))
            self.layout.note(ALLOCATION)
            for stage in stages:
                if self._hosts.get(stage) != allocation[stage]:
                    self._hosts[stage] = allocation[stage]
                    self.state(host_path(stage), t_s, allocation[stage])
        except Exception as exc:  # noqa: BLE001
            self._fail("allocation graph", exc)

    def network(self, t_s: float, network, all_links: Iterable = ()) -> None:
        """The links in use (a graph), and per link up/down and medium when they change.

        `all_links` are the topology's links (objects with ``a`` and ``b``); those missing from
        `network` are logged as down.
        """
        if self.stream is None:
            return
        try:
            rr = self.rr
            self.stream.set_time(TIMELINE, duration=float(t_s))
            self.stream.log(NETWORK, rr.GraphNodes(node_ids=list(network.nodes), labels=list(network.nodes)),
                            rr.GraphEdges(edges=[(l.a, l.b) for l in network.links], graph_type="undirected"))
            self.layout.note(NETWORK)
            now: dict[str, tuple[bool, str | None]] = {}
            for spec in all_links:
                now[link_path(spec.a, spec.b)] = (False, None)
            for link in network.links:
                now[link_path(link.a, link.b)] = (True, link.medium)
            for path, (up, medium) in now.items():
                if self._links.get(path) != (up, medium):
                    self.scalar(f"{path}/up", t_s, 1.0 if up else 0.0)
                    self.state(f"{path}/state", t_s, medium if up else "down")
                    self.text(f"{path}/medium", t_s, medium if up else "down", "INFO" if up else "WARN")
            self._links = now
        except Exception as exc:  # noqa: BLE001
            self._fail("network graph", exc)

    # ---- flushing ------------------------------------------------------------------------------------
    def flush(self) -> None:
        """Send everything buffered with one ``send_columns`` per entity."""
        scalars, texts, states = self._scalars, self._texts, self._states
        self._scalars, self._texts, self._states, self._rows = {}, {}, {}, 0
        if self.stream is None:
            return
        rr = self.rr
        for entity, (times, values) in scalars.items():
            try:
                self.layout.note(entity, values, times)
                self._style(entity)
                self.stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                                         columns=rr.Scalars.columns(scalars=values))
            except Exception as exc:  # noqa: BLE001
                self._fail("send scalars", exc)
        for entity, (times, values) in states.items():
            try:
                self.layout.note(entity)
                self.stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                                         columns=rr.StateChange.columns(state=values))
            except Exception as exc:  # noqa: BLE001
                self._fail("send states", exc)
        for entity, (times, lines, levels) in texts.items():
            try:
                self.layout.note(entity)
                self.stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                                         columns=rr.TextLog.columns(text=lines, level=levels))
            except Exception as exc:  # noqa: BLE001
                self._fail("send text", exc)
        try:
            self.stream.flush()
        except Exception as exc:  # noqa: BLE001
            self._fail("flush", exc)

    def _style(self, entity: str) -> None:
        """Once per entity: its static legend name, colour and (for states) step interpolation."""
        if entity in self._styled:
            return
        self._styled.add(entity)
        style = series_style(self.rr, entity)
        if style is not None:
            self.stream.log(entity, style, static=True)

    def close(self) -> None:
        self._end_predictions()
        self.flush()
        try:
            if self.stream is not None and self._blueprint is not None:
                self.stream.send_blueprint(self._blueprint(self.layout), make_active=True, make_default=True)
        except Exception as exc:  # noqa: BLE001
            self._fail("blueprint", exc)
        try:
            if self.stream is not None:
                self.stream.disconnect()
        except Exception as exc:  # noqa: BLE001
            self._fail("close", exc)
        self.stream = None

    def __enter__(self) -> "Telemetry":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _property_value(value: Any) -> Any:
    if isinstance(value, (str, int, float, bool)):
        return value
    return str(value)


# ---------------------------------------------------------------------------------------------
# Reading a recording back (tests, replay)
# ---------------------------------------------------------------------------------------------


class Recording:
    """The AutoPower view of an .rrd file: properties, scalar series and text logs by entity."""

    def __init__(self, properties: dict[str, Any], scalars: dict[str, tuple[list[float], list[float]]],
                 texts: dict[str, list[tuple[float, str, str]]], graphs: dict[str, list[tuple[float, list, list]]],
                 layout: Layout | None = None):
        self.properties = properties
        self.scalars = scalars
        self.texts = texts
        self.graphs = graphs
        self.layout = layout or Layout()

    def series(self, entity: str) -> tuple[list[float], list[float]]:
        times, values = self.scalars.get(entity, ([], []))
        order = sorted(range(len(times)), key=lambda i: times[i])
        return [times[i] for i in order], [values[i] for i in order]

    def log(self, entity: str) -> list[tuple[float, str, str]]:
        return sorted(self.texts.get(entity, []), key=lambda row: row[0])


def read_recording(path: str | Path) -> Recording:
    """Load an AutoPower recording; `RecordingError` if it is missing, corrupt or foreign."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such recording file")
    try:
        import pyarrow as pa
        from rerun.chunk import RrdReader

        chunks = RrdReader(str(path)).stream().to_chunks()
    except Exception as exc:  # noqa: BLE001 - the reader raises assorted types on garbage
        raise RecordingError(f"{path}: not a readable Rerun recording ({type(exc).__name__}: {exc})") from None
    props: dict[str, Any] = {}
    scalars: dict[str, tuple[list[float], list[float]]] = {}
    texts: dict[str, list[tuple[float, str, str]]] = {}
    graphs: dict[str, list[tuple[float, list, list]]] = {}
    layout = Layout()
    for chunk in chunks:
        entity = str(chunk.entity_path).lstrip("/")
        batch = chunk.to_record_batch()
        names = batch.schema.names
        if not entity.startswith("__"):
            layout.entities.add(entity)
        if entity == f"__properties/{PROPERTY}":
            for name in names:
                if name.startswith("rerun.") or name in ("log_time", "log_tick"):
                    continue
                values = batch.column(name).to_pylist()
                if values:
                    v = values[-1]
                    props[name.split(":")[-1]] = v[0] if isinstance(v, list) and len(v) == 1 else v
            continue
        if TIMELINE not in names:
            continue
        times = [t / 1e9 for t in batch.column(TIMELINE).cast(pa.int64()).to_pylist()]
        if "Scalars:scalars" in names:
            values = [v[0] if v else math.nan for v in batch.column("Scalars:scalars").to_pylist()]
            series = scalars.setdefault(entity, ([], []))
            series[0].extend(times)
            series[1].extend(values)
            layout.note(entity, values, times)
        if "TextLog:text" in names:
            lines = batch.column("TextLog:text").to_pylist()
            levels = batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(lines)
            rows = texts.setdefault(entity, [])
            for t, line, level in zip(times, lines, levels, strict=False):
                rows.append((t, _one(line), _one(level)))
        if "GraphEdges:edges" in names:
            nodes = batch.column("GraphNodes:node_ids").to_pylist() if "GraphNodes:node_ids" in names else []
            edges = batch.column("GraphEdges:edges").to_pylist()
            rows = graphs.setdefault(entity, [])
            for k, t in enumerate(times):
                rows.append((t, nodes[k] if k < len(nodes) else None, edges[k]))
    if props.get("layout") is None:
        raise RecordingError(f"{path}: a Rerun recording, but not an AutoPower run (no '{PROPERTY}' property)")
    return Recording(props, scalars, texts, graphs, layout)


def _one(value):
    if isinstance(value, list):
        return value[0] if value else None
    return value
