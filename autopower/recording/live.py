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
               recorder.record_stop(process.runtime)                          # produced per run, frames in flight
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

import math
import time
import zlib
from pathlib import Path

from autopower.recording.merge import merge_recordings, merge_run
from autopower.recording.recorder import MERGED_NAME, Recorder, run_recording_id

__all__ = ["MERGED_NAME", "OutputDrawer", "draw_output", "merge_recordings", "merge_run", "open_recorder",
           "run_recording_id"]


CAMERA_DOWNSCALE = 2  # the camera frame is logged at 160x120 (JPEG): victims visible, a few KB each
CAMERA_EVERY_S = 2.0  # wall seconds between camera frames of one chain (boxes come with their frame)


def draw_output(rr, chain: str, data: bytes, *, seq: int | None = None, scenario=None) -> list[tuple]:
    """Blobs as boxes on the camera image's pixel frame at 1/`CAMERA_DOWNSCALE` size, with that frame
    when `scenario` and `seq` say which; MCL particles and pose on the map (m), with the map."""
    from autopower.chains import decode_estimate, decode_report

    try:
        report = decode_report(data)
    except Exception:  # noqa: BLE001 - not a blob report: try the next kind
        report = None
    if report is not None:
        k = CAMERA_DOWNSCALE
        blobs = report.blobs
        drawn = [("blobs", rr.Boxes2D(
            mins=[(b.bbox_px[0] / k, b.bbox_px[1] / k) for b in blobs],
            sizes=[((b.bbox_px[2] - b.bbox_px[0] + 1) / k, (b.bbox_px[3] - b.bbox_px[1] + 1) / k) for b in blobs],
            labels=[b.colour for b in blobs], colors=(255, 255, 255)))]  # white: visible on any victim
        frame = _camera_frame(scenario, chain, seq)
        if frame is not None:
            drawn.insert(0, ("camera", rr.Image(frame).compress(jpeg_quality=75)))
        return drawn
    team_map = _team_map(rr, data)
    if team_map is not None:
        return team_map
    try:
        est = decode_estimate(data)
    except Exception:  # noqa: BLE001 - an output kind we do not draw
        return []
    drawn = [("particles", rr.Points2D(est.particles[:, :2], radii=0.05, colors=(120, 170, 255))),
             ("pose", rr.Points2D([est.pose[:2]], radii=0.25, colors=(255, 80, 40), labels=["estimate"]))]
    occupied = _map_points(scenario, chain)
    if occupied is not None:
        drawn.insert(0, ("map", rr.Points2D(occupied, radii=0.05, colors=(150, 150, 150)), True))
    return drawn


def _team_map(rr, data: bytes) -> list[tuple] | None:
    """A TeamMap output (a DAG fan-in, docs/concepts/chains.md): the explored cells, each
    robot's merged pose, and which inputs the step joined or ran without."""
    from autopower.chains.teammap import CELL_M, CELLS, decode_map

    try:
        out = decode_map(data)
    except Exception:  # noqa: BLE001 - not a team map
        return None
    import numpy as np

    grid = np.unpackbits(np.frombuffer(out["grid"], dtype=np.uint8)).reshape(CELLS, CELLS).astype(bool)
    rows, cols = np.nonzero(grid)
    robots = sorted(out["robots"])
    joined = [r for r in robots if out["robots"][r]["age_steps"] == 0]
    return [("explored", rr.Points2D(np.column_stack([(cols + 0.5) * CELL_M, (rows + 0.5) * CELL_M]),
                                     radii=CELL_M / 2, colors=(90, 200, 120))),
            ("poses", rr.Points2D([out["robots"][r]["pose"][:2] for r in robots], radii=0.3,
                                  colors=(255, 80, 40), labels=robots)),
            ("join", rr.TextDocument(f"step {out['step']}: joined {', '.join(joined) or 'none'}; "
                                     f"missing {', '.join(out['missing']) or 'none'}; "
                                     f"explored {out['explored_m2']:.1f} m²"))]


def _chain_seed(scenario, chain) -> int:
    # the agents' seed (autopower.node.stages.chain_seed; an upward import from here): a test checks they agree
    return zlib.crc32(f"{scenario.name}/{chain.name}".encode())


def _chain(scenario, name: str):
    if scenario is None:
        return None
    return next((c for c in scenario.chains if c.name == name), None)


def _camera_frame(scenario, name: str, seq: int | None):
    """The frame the chain's camera took at `seq`, downscaled (the source is deterministic in seq)."""
    chain = _chain(scenario, name)
    if chain is None or seq is None or chain.stages[0].component != "Blob":
        return None
    from autopower.chains import make_source

    image = make_source("Blob", chain.source, _chain_seed(scenario, chain)).camera.render(int(seq))
    k = CAMERA_DOWNSCALE
    h, w = image.shape[0] // k * k, image.shape[1] // k * k
    return image[:h, :w].reshape(h // k, k, w // k, k, 3).mean(axis=(1, 3)).astype("uint8")


def _map_points(scenario, name: str):
    """Centres (m) of the occupied cells of the building the chain's robot localises in."""
    chain = _chain(scenario, name)
    if chain is None or chain.stages[0].component != "Loc":
        return None
    import numpy as np

    from autopower.chains.world import make_building

    building = make_building(_chain_seed(scenario, chain))
    rows, cols = np.nonzero(building.occupied)
    return np.column_stack([(cols + 0.5) * building.resolution_m, (rows + 0.5) * building.resolution_m])


class OutputDrawer:
    """The recorder's `Visualiser` for a scenario: `draw_output`, a camera frame every `camera_every_s`
    per chain (its boxes with it, so they match), the map once per chain."""

    def __init__(self, scenario=None, camera_every_s: float = CAMERA_EVERY_S):
        self.scenario = scenario
        self.camera_every_s = camera_every_s
        self._camera_at: dict[str, float] = {}
        self._mapped: set[str] = set()

    def __call__(self, rr, chain: str, seq: int, data: bytes) -> list[tuple]:
        spec = _chain(self.scenario, chain)
        kind = spec.stages[0].component if spec is not None else None
        if kind == "Blob":
            now = time.monotonic()
            if now - self._camera_at.get(chain, -math.inf) < self.camera_every_s:
                return []
            self._camera_at[chain] = now
        drawn = draw_output(rr, chain, data, seq=seq, scenario=self.scenario if chain not in self._mapped
                            or kind == "Blob" else None)
        if kind == "Loc" and any(what == "map" for what, *_ in drawn):
            self._mapped.add(chain)
        return drawn


class QualityScorer:
    """The recorder's quality hook: each output at its sink scored against the synthetic world's
    ground truth, with the quality variant the plan runs (`autopower.chains.variants`: blob recall
    over every camera frame, localisation position error). Chains of other types, or without a
    scenario: nothing."""

    def __init__(self, scenario=None):
        self.scenario = scenario
        self._sources: dict[tuple[str, str | None], object] = {}

    def __call__(self, chain: str, seq: int, data: bytes, variants: dict) -> dict[str, float]:
        from autopower.chains.registry import make_source, score_output
        from autopower.chains.variants import measured_quality

        spec = _chain(self.scenario, chain)
        kind = spec.stages[0].component if spec is not None else None
        if kind not in ("Blob", "Loc"):
            return {}
        variant = variants.get(chain)
        key = (chain, variant)
        if key not in self._sources:
            params = next((dict(v.parameters) for v in self.scenario.components[kind].variants
                           if v.name == variant), {})
            self._sources[key] = make_source(kind, spec.source, _chain_seed(self.scenario, spec), params or None)
        return measured_quality(kind, self._sources[key], seq, data, score_output)


def open_recorder(run_dir: str | Path, node: str, *, scenario=None, **kwargs) -> Recorder:
    """A `Recorder` writing ``<run_dir>/<node>.rrd`` (the run's shared recording id), drawing outputs
    and scoring their quality."""
    kwargs.setdefault("visualise", OutputDrawer(scenario))
    kwargs.setdefault("quality", QualityScorer(scenario))
    return Recorder.open(run_dir, node, scenario=scenario, **kwargs)
