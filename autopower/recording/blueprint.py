"""The view a recording opens on: a Rerun blueprint designed from what the recording holds.

Without one, the viewer guesses (a dozen panels, most of them one arbitrary series each, and the
native and web viewers guess differently). `design` lays out, from a `Layout`:

- top: one plot of every robot's battery, measured, with the model's predicted line and where it
  predicts empty; beside it, per robot (tabs), the power it draws split by part;
- middle: where each stage runs (the allocation graph) and the network links in use (tabs); the
  links up/down and robots alive as steps; link media and stage hosts as lanes over time;
- bottom: the chains (outputs received, end-to-end latency, missing and duplicated outputs), a
  downscaled camera frame with the blob finder's boxes, MCL particles and pose on the map; and
  the timeline of faults, decisions and migrations at INFO and above (protocol chatter is logged
  to ``events/messages`` and left out).

Views whose data a recording lacks (a simulation has no chain outputs) are left out. The
query language has no wildcards but ``/**``, so views list their entities from the layout.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from autopower.recording.telemetry import (
    ALLOCATION,
    DECISIONS,
    FAULTS,
    HOSTS,
    LINKS,
    MIGRATIONS,
    NETWORK,
    READABLE,
    TIMELINE,
    Layout,
    alive_path,
    battery_path,
    depletion_path,
    predicted_path,
)

__all__ = ["design", "blueprint_views", "INFO_LEVELS"]

INFO_LEVELS = ["CRITICAL", "ERROR", "WARN", "INFO"]


def _plot(rrb, name: str, contents: list[str], *, span: tuple[float, float] | None,
          y: tuple[float, float] | None = None, legend: bool = True):
    # the whole mission, not the viewer's default window around the time cursor (an infinite range
    # draws nothing in 0.41)
    whole = None if span is None else rrb.TimeAxis(view_range=rrb.TimeRange(
        start=rrb.TimeRangeBoundary.absolute(seconds=span[0]), end=rrb.TimeRangeBoundary.absolute(seconds=span[1])))
    return rrb.TimeSeriesView(
        name=name, origin="/", contents=[f"+ /{e}" for e in contents], axis_x=whole,
        axis_y=rrb.ScalarAxis(range=y, zoom_lock=False) if y is not None else None,
        plot_legend=rrb.PlotLegend(corner="RightTop", visible=legend))


def _tabs(rrb, views: list, **kwargs):
    views = [v for v in views if v is not None]
    if not views:
        return None
    return views[0] if len(views) == 1 else rrb.Tabs(*views, **kwargs)


def _row(rrb, parts: list, shares: list[float] | None = None):
    kept = [(p, s) for p, s in zip(parts, shares or [1.0] * len(parts), strict=False) if p is not None]
    if not kept:
        return None
    if len(kept) == 1:
        return kept[0][0]
    return rrb.Horizontal(*[p for p, _ in kept], column_shares=[s for _, s in kept])


def design(layout: Layout) -> Any:
    """The blueprint (``rerun.blueprint.Blueprint``) for a recording with this layout."""
    import rerun.blueprint as rrb

    robots = layout.robots()
    has = layout.entities.__contains__
    top_pad = 1.05
    span = (layout.start_s, layout.end_s) if layout.end_s > layout.start_s else None

    battery = [e for r in robots for e in (battery_path(r), predicted_path(r), depletion_path(r)) if has(e)]
    battery_view = _plot(rrb, "Battery (J): measured, model's prediction, predicted empty", battery, span=span,
                         y=(0.0, layout.battery_max_j * top_pad) if layout.battery_max_j > 0 else None) \
        if battery else None
    power_views = [_plot(rrb, f"{r}: power by part (W)", [e for e in layout.under(f"robots/{r}/power_w")], span=span,
                         y=(0.0, layout.power_max_w * top_pad) if layout.power_max_w > 0 else None)
                   for r in robots if layout.under(f"robots/{r}/power_w")]

    graphs = [rrb.GraphView(origin=f"/{ALLOCATION}", name="Where each stage runs") if has(ALLOCATION) else None,
              rrb.GraphView(origin=f"/{NETWORK}", name="Network links in use") if has(NETWORK) else None]
    steps = [e for e in layout.under(LINKS) if e.endswith("/up")] + [alive_path(r) for r in robots
                                                                     if has(alive_path(r))]
    steps_view = _plot(rrb, "Links up (1) or cut (0), robots alive", steps, span=span, y=(-0.1, 1.1)) if steps else None
    lanes = [e for e in layout.under(LINKS) if e.endswith("/state")] + layout.under(HOSTS)
    lanes_view = rrb.StateTimelineView(name="Link media and stage hosts over time", origin="/",
                                       contents=[f"+ /{e}" for e in lanes]) if lanes else None

    chains = layout.chains()
    outputs = [e for c in chains for e in layout.under(f"components/{c}/sink") if e.endswith("/received_total")]
    latency = [e for c in chains for e in layout.under(f"components/{c}/sink") if "/latency_ms" in e]
    losses = [e for c in chains for e in layout.under(f"components/{c}/sink")
              if e.endswith(("/duplicates_total", "/missing"))]
    chain_views = [_plot(rrb, "Outputs received per chain", outputs, span=span) if outputs else None,
                   _plot(rrb, "End-to-end latency per chain (ms)", latency, span=span) if latency else None,
                   _plot(rrb, "Missing and duplicated outputs per chain", losses, span=span) if losses else None]
    cameras = [rrb.Spatial2DView(origin=f"/components/{c}", name=f"{c}: camera (1/2 size) and blobs found",
                                 contents=["+ $origin/camera", "+ $origin/blobs"])
               for c in chains if has(f"components/{c}/camera") or has(f"components/{c}/blobs")]
    maps = [rrb.Spatial2DView(origin=f"/components/{c}", name=f"{c}: MCL particles and pose on the map",
                              contents=["+ $origin/map", "+ $origin/particles", "+ $origin/pose"])
            for c in chains if has(f"components/{c}/particles")]
    # live events carry a JSON tail for replay; their readable copies are what a person wants
    events = layout.under(READABLE) or [e for e in (FAULTS, DECISIONS, MIGRATIONS) if has(e)]
    events_view = rrb.TextLogView(name="Faults, decisions and migrations", origin="/",
                                  contents=[f"+ /{e}" for e in events],
                                  rows=rrb.TextLogRows(filter_by_log_level=INFO_LEVELS)) if events else None

    rows = [
        (_row(rrb, [battery_view, _tabs(rrb, power_views)], [3.0, 2.0]), 3.0),
        (_row(rrb, [_tabs(rrb, graphs), _tabs(rrb, [steps_view, lanes_view])], [1.0, 1.0]), 3.0),
        (_row(rrb, [_tabs(rrb, chain_views), _tabs(rrb, cameras), _tabs(rrb, maps)], [1.0, 1.0, 1.0]), 3.0),
        (events_view, 2.0),
    ]
    kept = [(r, s) for r, s in rows if r is not None]
    root = rrb.Vertical(*[r for r, _ in kept], row_shares=[s for _, s in kept]) if kept else rrb.Vertical()
    return rrb.Blueprint(root, rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         # a file opens at its end on mission time: every plot whole, the last frame drawn
                         rrb.TimePanel(state="collapsed", timeline=TIMELINE, play_state="following"),
                         auto_views=False)


def blueprint_views(path: str | Path) -> list[dict[str, Any]]:
    """The views of the blueprint(s) stored in an .rrd: name, kind, origin, contents, y_range (tests, tools)."""
    from rerun.chunk import RrdReader

    reader = RrdReader(str(path))
    views: dict[str, dict[str, Any]] = {}
    for store in reader.blueprints():
        for chunk in reader.stream(store=store).to_chunks():
            entity = str(chunk.entity_path)
            if not entity.startswith("/view/"):
                continue
            view_id = entity.split("/")[2]
            batch = chunk.to_record_batch()
            view = views.setdefault(view_id, {"name": None, "kind": None, "origin": None, "contents": [],
                                              "y_range": None})
            for column, key in (("ViewBlueprint:display_name", "name"), ("ViewBlueprint:class_identifier", "kind"),
                                ("ViewBlueprint:space_origin", "origin"), ("ViewContents:query", "contents"),
                                ("ScalarAxis:range", "y_range")):
                if column in batch.schema.names:
                    value = batch.column(column).to_pylist()[-1]
                    if key == "contents":
                        view[key] = list(value or [])
                    else:
                        view[key] = value[0] if isinstance(value, list) and value else value
    return list(views.values())
