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
``robots/<robot>/power_w/<part>``  Scalars                     by part: ``cpu``, ``<medium>/send``,
                                                               ``<medium>/receive``, ``<medium>/sleep``
                                                               (a live status's ``802.11a:send`` maps to
                                                               ``802.11a/send``)
``team/allocation``                GraphNodes + GraphEdges     nodes and stages; a directed edge
                                                               stage → host, logged at every change
``team/network``                   GraphNodes + GraphEdges     the links in use (undirected)
``team/links/<a>-<b>/up``          Scalars                     1 while the link exists, 0 while cut
``team/links/<a>-<b>/medium``      TextLog                     the medium it uses, at every change
``events/faults``                  TextLog (WARN)              link cuts/heals, radio faults, chains on/off,
                                                               robots joining/leaving, energy offsets
``events/migrations``              TextLog (INFO)              each move: stage, hosts, bytes, joules,
                                                               missed periods
``events/decisions``               TextLog (INFO)              every policy decision's reasons
``components/<stage>/...``         (reserved)                  component outputs (blobs, particles)
=================================  ==========================  ===========================================

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
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

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


def new_recording_id() -> str:
    return str(uuid.uuid4())


class Telemetry:
    """A Rerun writer with the AutoPower layout that never raises into its caller."""

    def __init__(self, path: str | Path | None, *, recording_id: str | None = None, kind: str = "simulation",
                 properties: Mapping[str, Any] | None = None, flush_rows: int = 100_000, stream=None):
        self.path = None if path is None else str(path)
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
        except Exception as exc:  # noqa: BLE001
            self._fail("text", exc)

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

    def log(self, entity: str, t_s: float, *archetypes) -> None:
        """Log archetypes (e.g. ``rr.Points2D``) now, at mission time `t_s`; never raises.

        For low-rate visual data (component outputs); numbers belong in `scalar` (batched).
        """
        if self.stream is None:
            return
        try:
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
            now: dict[str, tuple[bool, str | None]] = {}
            for spec in all_links:
                now[link_path(spec.a, spec.b)] = (False, None)
            for link in network.links:
                now[link_path(link.a, link.b)] = (True, link.medium)
            for path, (up, medium) in now.items():
                if self._links.get(path) != (up, medium):
                    self.scalar(f"{path}/up", t_s, 1.0 if up else 0.0)
                    self.text(f"{path}/medium", t_s, medium if up else "down", "INFO" if up else "WARN")
            self._links = now
        except Exception as exc:  # noqa: BLE001
            self._fail("network graph", exc)

    # ---- flushing ------------------------------------------------------------------------------------
    def flush(self) -> None:
        """Send everything buffered with one ``send_columns`` per entity."""
        scalars, texts = self._scalars, self._texts
        self._scalars, self._texts, self._rows = {}, {}, 0
        if self.stream is None:
            return
        rr = self.rr
        for entity, (times, values) in scalars.items():
            try:
                self.stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                                         columns=rr.Scalars.columns(scalars=values))
            except Exception as exc:  # noqa: BLE001
                self._fail("send scalars", exc)
        for entity, (times, lines, levels) in texts.items():
            try:
                self.stream.send_columns(entity, indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                                         columns=rr.TextLog.columns(text=lines, level=levels))
            except Exception as exc:  # noqa: BLE001
                self._fail("send text", exc)
        try:
            self.stream.flush()
        except Exception as exc:  # noqa: BLE001
            self._fail("flush", exc)

    def close(self) -> None:
        self.flush()
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
                 texts: dict[str, list[tuple[float, str, str]]], graphs: dict[str, list[tuple[float, list, list]]]):
        self.properties = properties
        self.scalars = scalars
        self.texts = texts
        self.graphs = graphs

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
    for chunk in chunks:
        entity = str(chunk.entity_path).lstrip("/")
        batch = chunk.to_record_batch()
        names = batch.schema.names
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
        if "TextLog:text" in names:
            lines = batch.column("TextLog:text").to_pylist()
            levels = batch.column("TextLog:level").to_pylist() if "TextLog:level" in names else [None] * len(lines)
            rows = texts.setdefault(entity, [])
            for t, line, level in zip(times, lines, levels):
                rows.append((t, _one(line), _one(level)))
        if "GraphEdges:edges" in names:
            nodes = batch.column("GraphNodes:node_ids").to_pylist() if "GraphNodes:node_ids" in names else []
            edges = batch.column("GraphEdges:edges").to_pylist()
            rows = graphs.setdefault(entity, [])
            for k, t in enumerate(times):
                rows.append((t, nodes[k] if k < len(nodes) else None, edges[k]))
    if props.get("layout") is None:
        raise RecordingError(f"{path}: a Rerun recording, but not an AutoPower run (no '{PROPERTY}' property)")
    return Recording(props, scalars, texts, graphs)


def _one(value):
    if isinstance(value, list):
        return value[0] if value else None
    return value
