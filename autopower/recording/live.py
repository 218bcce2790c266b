"""Recording a live run: the deploy layer's glue between the processes and `autopower.recording.recorder`.

It lives here (not in the core) because drawing a component's output needs the chains'
decoders. Processes call `open_recorder` once, wrap their bus with ``recorder.tap(bus)`` and
hand their `NodeRuntime` to ``recorder.attach``; the launcher calls `merge_run` at the end.

Integration recipe (what the `agent` / `basestation` commands and the launcher do):

1. `agent` and `basestation` take ``--record-dir DIR``; with it::

       recorder = open_recorder(record_dir, robot, scenario=scenario)      # or scenario.basestation
       bus = recorder.tap(ZenohBus(config.zenoh))
       try:
           with Agent(config, bus=bus) as process:                        # BaseStation(config, host_factory=NodeRuntime, bus=bus)
               recorder.attach(process.runtime)
               reason = run_until_signalled(process, duration)
       finally:
           bus.close()   # flushes the .rrd: must run before any os._exit; BaseStation does not close a given bus

2. The launcher passes ``--record-dir runs/<run-id>`` to every child and calls
   ``merge_run(run_dir)`` after stopping them -> ``runs/<run-id>/run.rrd``.
3. Fault tools call ``record_fault_event(run_dir, kind="cut"|"kill"|"freeze"|"radio",
   target="r1-laptop"|"r2", mission=snapshot["mission"])`` after each injection (``phase="healed"``
   for heals), so replay can report detection and reconfiguration times.
4. The demo's summary is ``autopower.recording.replay.replay_summary(run_dir / "run.rrd")``: ``faults``
   (kind, target, parts, detected/reconfigured in ``_wall_s`` and ``_mission_s``), ``migrations``,
   ``lost_outputs``, ``duplicated_outputs``, ``energy_model_error_pct``. `tests/integration/recorder_node.py` runs this recipe.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from autopower.recording.merge import merge_recordings, merge_run
from autopower.recording.recorder import MERGED_NAME, Recorder, run_recording_id

__all__ = ["MERGED_NAME", "draw_output", "merge_recordings", "merge_run", "open_recorder", "run_recording_id"]


def draw_output(rr, chain: str, data: bytes) -> list[tuple[str, Any]]:
    """Blobs as boxes on the camera image's pixel frame; MCL particles and pose on the map (m)."""
    from autopower.chains import decode_estimate, decode_report

    try:
        report = decode_report(data)
    except Exception:  # noqa: BLE001 - not a blob report: try the next kind
        report = None
    if report is not None:
        blobs = report.blobs
        return [("blobs", rr.Boxes2D(
            mins=[(b.bbox_px[0], b.bbox_px[1]) for b in blobs],
            sizes=[(b.bbox_px[2] - b.bbox_px[0] + 1, b.bbox_px[3] - b.bbox_px[1] + 1) for b in blobs],
            labels=[b.colour for b in blobs]))]
    try:
        est = decode_estimate(data)
    except Exception:  # noqa: BLE001 - an output kind we do not draw
        return []
    return [("particles", rr.Points2D(est.particles[:, :2], radii=0.05)),
            ("pose", rr.Points2D([est.pose[:2]], radii=0.15))]


def open_recorder(run_dir: str | Path, node: str, *, scenario=None, **kwargs) -> Recorder:
    """A `Recorder` writing ``<run_dir>/<node>.rrd`` (the run's shared recording id), drawing outputs."""
    kwargs.setdefault("visualise", draw_output)
    return Recorder.open(run_dir, node, scenario=scenario, **kwargs)
