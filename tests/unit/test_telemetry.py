"""Rerun telemetry: the layout round-trips through a real .rrd file; logging failures never stop a run."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest

from autopower.errors import RecordingError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events
from autopower.recording.telemetry import (
    ALLOCATION,
    DECISIONS,
    FAULTS,
    MIGRATIONS,
    NETWORK,
    Telemetry,
    battery_path,
    link_path,
    power_path,
    read_recording,
)
from autopower.simulation.simulator import simulate

os.environ.setdefault("RERUN_ANALYTICS", "0")
FIG7 = load_scenario("paper-fig7")
RERUN = Path(sys.executable).parent / "rerun"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    path = tmp_path_factory.mktemp("rrd") / "run.rrd"
    script = load_events("link-cuts", FIG7)
    with Telemetry(path, properties={"scenario": FIG7.name, "policy": "reactive", "seed": 3}) as tel:
        result = simulate(FIG7, script, policy="reactive", seed=3, telemetry=tel)
    assert tel.errors == 0
    return path, result, tel.recording_id


def test_the_recording_verifies_with_the_rerun_cli(run):
    path, _, _ = run
    out = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60,
                         env={**os.environ, "RERUN_ANALYTICS": "0"})
    assert out.returncode == 0, out.stderr


def test_properties_identify_an_autopower_run(run):
    path, _, recording_id = run
    rec = read_recording(path)
    assert rec.properties["kind"] == "simulation" and rec.properties["layout"] == 1
    assert rec.properties["scenario"] == "paper-fig7" and rec.properties["policy"] == "reactive"
    assert rec.properties["recording_id"] == recording_id


def test_battery_and_power_follow_the_simulation(run):
    path, result, _ = run
    rec = read_recording(path)
    times, joules = rec.series(battery_path("r1"))
    assert times[0] == 0.0 and joules[0] == 64000.0
    assert times[-1] == pytest.approx(result.lifetime_s, abs=1e-6)
    assert joules[-1] == pytest.approx(result.final_energies_j["r1"], abs=1e-3)
    # battery is piecewise linear: every segment's drain is its power times its length
    for seg in result.segments:
        if "r1" in seg.power_w and seg.end_s > seg.start_s:
            # at an instant the battery is sampled before and after any migration's charge
            start = [j for t, j in zip(times, joules, strict=False) if t == pytest.approx(seg.start_s, abs=1e-6)][-1]
            end = [j for t, j in zip(times, joules, strict=False) if t == pytest.approx(seg.end_s, abs=1e-6)][0]
            assert start - end == pytest.approx(seg.power_w["r1"] * (seg.end_s - seg.start_s), rel=1e-6, abs=1e-3)
    t_power, watts = rec.series(power_path("r2"))
    assert watts[0] == pytest.approx(result.segments[0].power_w["r2"])
    assert rec.series(power_path("r2", "cpu"))[1] and rec.series(power_path("r2", "802.11a:sleep"))[1]
    # r2 left the team at 12000 s: no samples while it was away
    assert not [t for t in rec.series(battery_path("r2"))[0] if 12000 < t < 13800]


def test_faults_migrations_decisions_and_links_are_logged(run):
    path, result, _ = run
    rec = read_recording(path)
    faults = rec.log(FAULTS)
    assert [t for t, _, _ in faults] == [t for t, _ in result.events]
    assert faults[0][1] == "link r1–laptop cut" and faults[0][2] == "WARN"
    assert len(rec.log(MIGRATIONS)) == len(result.migrations)
    assert any("cold start (state lost)" in line for _, line, _ in rec.log(MIGRATIONS))
    assert rec.log(DECISIONS)[-1][1].startswith("mission over at")
    up = rec.series(link_path("r1", "laptop") + "/up")
    assert list(zip(*up, strict=True)) == [(0.0, 1.0), (3600.0, 0.0), (9000.0, 1.0)]
    assert rec.log(link_path("laptop", "r1") + "/medium")[0][1] == "802.11a"
    graph = rec.graphs[ALLOCATION]
    assert len(graph) == len(result.decisions)
    t0, nodes, edges = graph[0]
    assert t0 == 0.0 and {"r1", "laptop", "Loc-1"} <= set(nodes)
    assert {"first": "Loc-1", "second": "laptop"} in edges
    assert rec.graphs[NETWORK]


class _Broken:
    """A Rerun stream whose every call fails (disk full, viewer gone, ...)."""

    def __getattr__(self, name):
        def fail(*args, **kwargs):
            raise OSError("no space left on device")
        return fail


def test_a_failing_sink_never_stops_the_simulation(caplog):
    script = load_events("paper-vc-fault", FIG7)
    plain = simulate(FIG7, script, policy="reactive")
    tel = Telemetry(None, stream=_Broken())
    with caplog.at_level(logging.WARNING, logger="autopower.recording.telemetry"):
        logged = simulate(FIG7, script, policy="reactive", telemetry=tel)
        tel.close()
    assert logged.to_dict() == plain.to_dict()
    assert tel.errors > 0
    warnings = [r.message for r in caplog.records]
    assert len(warnings) == len(set(warnings)) and any("no space left on device" in w for w in warnings)


def test_an_unwritable_path_is_a_warning_not_a_crash(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    tel = Telemetry(blocker / "sub" / "run.rrd")
    tel.battery(0.0, "r1", 1.0)
    tel.close()
    assert tel.errors >= 1


def test_many_rows_are_flushed_in_batches(tmp_path):
    path = tmp_path / "many.rrd"
    with Telemetry(path, flush_rows=1000) as tel:
        for k in range(5000):
            tel.battery(float(k), "r1", 5000.0 - k)
    times, values = read_recording(path).series(battery_path("r1"))
    assert len(times) == 5000 and values[:2] == [5000.0, 4999.0]


def test_garbage_and_foreign_files_are_rejected(tmp_path):
    garbage = tmp_path / "garbage.rrd"
    garbage.write_bytes(b"\x00not a recording at all" * 10)
    with pytest.raises(RecordingError, match="not a readable Rerun recording"):
        read_recording(garbage)
    with pytest.raises(RecordingError, match="no such recording file"):
        read_recording(tmp_path / "missing.rrd")
    import rerun as rr

    foreign = tmp_path / "foreign.rrd"
    stream = rr.RecordingStream("someone-else", recording_id="x")
    stream.save(str(foreign))
    stream.set_time("t", sequence=1)
    stream.log("x", rr.Scalars(1.0))
    stream.flush()
    stream.disconnect()
    with pytest.raises(RecordingError, match="not an AutoPower run"):
        read_recording(foreign)


def test_entity_paths():
    assert battery_path("r1") == "robots/r1/battery_j"
    assert power_path("r1", "802.11a:send") == "robots/r1/power_w/802.11a/send"
    assert power_path("r1") == "robots/r1/power_w/total"
    assert link_path("r2", "laptop") == link_path("laptop", "r2") == "team/links/laptop-r2"
