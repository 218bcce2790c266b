"""The view a recording opens on: the blueprint is in the file (read back), the entities it shows
exist, states are steps, the camera frame is there and small, protocol chatter stays off the
events timeline."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events
from autopower.recording.blueprint import blueprint_views, design
from autopower.recording.live import CAMERA_DOWNSCALE, OutputDrawer, open_recorder
from autopower.recording.merge import merge_run
from autopower.recording.telemetry import (
    DECISIONS,
    EVENT_TAG,
    MESSAGES,
    MIGRATIONS,
    READABLE,
    Telemetry,
    alive_path,
    battery_path,
    depletion_path,
    host_path,
    link_path,
    link_state_path,
    predicted_path,
    read_recording,
)
from autopower.runtime.bus import InMemoryBus
from autopower.simulation.simulator import simulate
from tests.unit import sim_team
from tests.unit.sim_team import SimTeam
from tests.unit.test_recorder import FC, _publish_status, _TappedHub

os.environ.setdefault("RERUN_ANALYTICS", "0")
FIG7 = load_scenario("paper-fig7")
ROBOTS = ("r1", "r2", "r3")


def _components(path: Path, entity: str) -> dict[str, list]:
    """Every component column logged on `entity` (static or not): name -> values, in file order."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(str(path)).stream().to_chunks():
        if str(chunk.entity_path).lstrip("/") != entity:
            continue
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if ":" in name:
                out.setdefault(name, []).extend(batch.column(name).to_pylist())
    return out


def _views(path: Path) -> dict[str, dict]:
    from rerun.chunk import RrdReader

    assert len(RrdReader(str(path)).blueprints()) == 1  # one view, or the viewer picks one at random
    return {v["name"]: v for v in blueprint_views(path)}


def _shown(view: dict) -> set[str]:
    return {q.removeprefix("+ /") for q in view["contents"] if q.startswith("+ /")}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    path = tmp_path_factory.mktemp("view") / "sim.rrd"
    with Telemetry(path, properties={"scenario": FIG7.name}, blueprint=design) as tel:
        result = simulate(FIG7, load_events("link-cuts", FIG7), policy="reactive", seed=3, telemetry=tel)
    assert tel.errors == 0
    return path, result


def test_a_simulated_recording_opens_on_batteries_power_graphs_links_and_events(simulated):
    path, _ = simulated
    views = _views(path)
    battery = views["Battery (J): measured, model's prediction, predicted empty"]
    assert battery["kind"] == "TimeSeries"
    assert _shown(battery) == {p(r) for r in ROBOTS for p in (battery_path, predicted_path, depletion_path)}
    for r in ROBOTS:
        assert f"robots/{r}/power_w/cpu" in _shown(views[f"{r}: power by part (W)"])
    assert views["Where each stage runs"]["kind"] == "Graph" and views["Network links in use"]["kind"] == "Graph"
    assert link_path("r1", "laptop") + "/up" in _shown(views["Links up (1) or cut (0), robots alive"])
    lanes = _shown(views["Link media and stage hosts over time"])
    assert link_state_path("r1", "laptop") in lanes and host_path("Loc-1") in lanes
    assert views["Link media and stage hosts over time"]["kind"] == "StateTimeline"
    events = views["Faults, decisions and migrations"]
    assert events["kind"] == "TextLog" and MESSAGES not in _shown(events)
    # every entity a view names exists in the recording
    entities = read_recording(path).layout.entities
    for view in views.values():
        assert _shown(view) <= entities, view["name"]


def test_the_predicted_line_starts_at_the_battery_and_ends_empty(simulated):
    path, result = simulated
    rec = read_recording(path)
    times, joules = rec.series(predicted_path("r1"))
    assert times[0] == 0.0 and joules[0] == 64000.0 and joules[-1] == 0.0
    empty_t, empty_j = rec.series(depletion_path("r1"))
    assert empty_j and set(empty_j) == {0.0}
    # the last prediction runs r1 dry where its line reaches 0
    assert any(abs(times[-1] - t) < 1e-6 for t in empty_t)
    # and the mission (the replay's end) is still the robots' last sample, not the prediction's
    assert max(rec.series(battery_path("r1"))[0]) == pytest.approx(result.lifetime_s)


def test_states_are_steps_with_a_meaningful_range(simulated):
    path, _ = simulated
    up = link_path("r1", "laptop") + "/up"
    style = _components(path, up)
    assert style["SeriesLines:interpolation_mode"] == [[2]]  # StepAfter, static
    _, values = read_recording(path).series(up)
    assert set(values) <= {0.0, 1.0} and all(a != b for a, b in zip(values, values[1:], strict=False))  # changes only
    views = _views(path)
    # plots start at 0 (no 1e-7 noise stretched to full height); states have room around 0 and 1
    assert views["r1: power by part (W)"]["y_range"][0] == 0.0
    assert views["Battery (J): measured, model's prediction, predicted empty"]["y_range"][0] == 0.0
    low, high = views["Links up (1) or cut (0), robots alive"]["y_range"]
    assert low < 0.0 and high > 1.0


def test_simulate_record_writes_the_view(tmp_path):
    out = tmp_path / "cli.rrd"
    done = subprocess.run([str(Path(sys.executable).parent / "autopower"), "simulate", "paper-fig7", "--events",
                           "paper-vc-fault", "--policy", "reactive", "--record", str(out), "--json"],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "RERUN_ANALYTICS": "0"})
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["recording"] == str(out)
    assert "Battery (J): measured, model's prediction, predicted empty" in _views(out)


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """An in-memory team, each process recorded as the live processes do (`open_recorder`), merged."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        return _record_live_run(tmp_path_factory.mktemp("live") / "run-7", monkeypatch)


def _record_live_run(run_dir: Path, monkeypatch):
    sc = load_scenario("paper-fig7")
    holder: list = []

    class Hub(_TappedHub):
        recorders: dict = {}

        def bus(self, name: str = ""):
            rec = open_recorder(run_dir, name, scenario=sc, clock=lambda: holder[0].t, visual_every_s=0.0,
                                visualise=OutputDrawer(sc, camera_every_s=0.0))
            self.recorders[name] = rec
            return rec.tap(InMemoryBus(self, name))

    monkeypatch.setattr(sim_team, "InMemoryHub", Hub)
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False), fake=False)
    holder.append(team.clock)
    for name, rt in team.nodes.items():
        Hub.recorders[name].attach(rt)
    team.join()
    for t in range(1, 13):
        team.run_until(float(t))
        if t % 2 == 0:
            _publish_status(team)
    for rec in Hub.recorders.values():
        rec.close()
    return merge_run(run_dir), run_dir


def test_a_merged_live_run_carries_one_view_with_chains_camera_and_map(live_run):
    merged, run_dir = live_run
    from rerun.chunk import RrdReader

    assert all(not RrdReader(str(p)).blueprints() for p in run_dir.glob("*.rrd") if p != merged)
    views = _views(merged)
    assert {"Outputs received per chain", "End-to-end latency per chain (ms)",
            "Missing and duplicated outputs per chain"} <= set(views)
    camera = views["Blob-2: camera (1/2 size) and blobs found"]
    assert camera["kind"] == "2D" and camera["origin"] == "/components/Blob-2"
    assert views["Loc-1: MCL particles and pose on the map"]["kind"] == "2D"
    entities = read_recording(merged).layout.entities
    for name in ("camera", "blobs"):
        assert f"components/Blob-2/{name}" in entities
    for name in ("map", "particles", "pose"):
        assert f"components/Loc-1/{name}" in entities
    for r in ROBOTS:
        assert alive_path(r) in entities and predicted_path(r) in entities
        assert _components(merged, alive_path(r))["SeriesLines:interpolation_mode"][0] == [2]  # steps
    assert "components/Blob-2/sink/latency_ms_p50" in entities


def test_the_camera_frame_is_small(live_run):
    merged, _ = live_run
    frames = _components(merged, "components/Blob-2/camera")
    jpegs = [bytes(row[0]) for row in frames["EncodedImage:blob"]]  # one image per row
    assert jpegs and all(len(j) < 20_000 for j in jpegs)  # JPEG, 1/2 size: a few KB, not 230 KB of PPM
    from io import BytesIO

    from PIL import Image

    width, height = Image.open(BytesIO(jpegs[0])).size
    assert (width, height) == (320 // CAMERA_DOWNSCALE, 240 // CAMERA_DOWNSCALE)
    boxes = _components(merged, "components/Blob-2/blobs")["Boxes2D:half_sizes"]
    assert boxes and all(0 < x <= width and 0 < y <= height for row in boxes for x, y in row)


def test_protocol_chatter_stays_off_the_events_timeline(live_run):
    merged, _ = live_run
    rec = read_recording(merged)
    assert rec.log(MESSAGES) and {level for _, _, level in rec.log(MESSAGES)} == {"DEBUG"}
    for entity in (DECISIONS, MIGRATIONS):
        assert all(level != "DEBUG" for _, _, level in rec.log(entity))
    # the events view shows them without the JSON tail replay parses (which stays in events/*)
    readable = rec.log(f"{READABLE}/decisions")
    assert readable and all(EVENT_TAG not in line for _, line, _ in readable)
    assert len(readable) == len(rec.log(DECISIONS)) and EVENT_TAG in rec.log(DECISIONS)[0][1]
    events_view = _views(merged)["Faults, decisions and migrations"]
    assert f"{READABLE}/decisions" in _shown(events_view) and DECISIONS not in _shown(events_view)


def test_the_drawer_uses_the_agents_chain_seed():
    from autopower.node.stages import chain_seed
    from autopower.recording.live import _chain_seed

    assert all(_chain_seed(FIG7, c) == chain_seed(FIG7, c) for c in FIG7.chains)
