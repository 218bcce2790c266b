"""Two real processes over real Zenoh on 127.0.0.1, each recording its own file; merged; replayed."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from autopower.recording.merge import merge_run
from autopower.recording.recorder import run_recording_id
from autopower.recording.replay import load, summarize
from autopower.recording.telemetry import read_recording

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_agent_and_base_station_record_one_run(tmp_path):
    run_dir = tmp_path / "run-zenoh"
    port = free_port()
    env = {**os.environ, "RERUN_ANALYTICS": "0", "PYTHONPATH": str(ROOT)}

    def spawn(role: str, seconds: float) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "tests.integration.recorder_node", role, str(run_dir),
                                 str(port), str(seconds)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)

    base = spawn("base", 9.0)
    agent = spawn("agent", 6.0)  # leaves first: the base station sees r1's liveliness go
    try:
        out_agent, _ = agent.communicate(timeout=40)
        out_base, _ = base.communicate(timeout=40)
    finally:
        for proc in (agent, base):
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert agent.returncode == 0 and base.returncode == 0, out_agent + out_base
    assert "recorder errors 0" in out_agent and "recorder errors 0" in out_base, out_agent + out_base
    assert {p.name for p in run_dir.glob("*.rrd")} == {"laptop.rrd", "r1.rrd"}
    for name in ("laptop.rrd", "r1.rrd"):
        assert read_recording(run_dir / name).properties["recording_id"] == run_recording_id(run_dir)

    merged = merge_run(run_dir)
    s = summarize(load(merged), merged)
    assert s["kind"] == "live" and set(s["robots"]) == {"r1"}
    assert s["robots"]["r1"]["used_j"] > 0 and s["mission"]["covered_s"] > 20  # speed 20, >= 3 s of statuses
    assert s["decisions"] >= 1
    chains = s["outputs"]["chains"]
    assert "Loc-1" in chains and chains["Loc-1"]["outputs"] >= 5, chains  # r1's own localisation, at r1
    assert s["lost_outputs"] == 0 and s["duplicated_outputs"] == 0
    lost = [f for f in s["faults"] if f["kind"] == "node-lost" and f["target"] == "r1"]
    assert lost, s["faults"]
    assert s["energy_model_error_pct"] is not None and abs(s["energy_model_error_pct"]) < 10
    assert s["ok"], s["invariants"]
