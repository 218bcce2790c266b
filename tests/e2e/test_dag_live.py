"""The DAG scenario live (docs/concepts/chains.md): real processes on Zenoh, the paper's
mission plus a TeamMap stage merging Loc-1..3, recorded in Rerun.

Loc-1 runs on r1 and the map on r2, so the three flows into the map cross real sessions (r1 -> r2,
laptop -> r2 twice) and the map goes r2 -> laptop; Loc-1's pose also still goes back to r1.
"""

from __future__ import annotations

import json

from tests.e2e.test_up import env_for, run_cli


def test_team_map_dag_runs_live_exactly_once_and_is_recorded(tmp_path):
    from rerun.chunk import RrdReader

    from autopower.recording.telemetry import read_recording

    env = env_for(tmp_path)
    run_dir = tmp_path / "runs" / "dag"
    result = run_cli(["up", "paper-teammap", "--duration", "10", "--json", "--pin", "Loc-1=r1", "--pin", "TeamMap=r2",
                      "--record-dir", str(run_dir), "--log-dir", str(tmp_path / "logs")], env, timeout=150)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["placement"]["Loc-1"] == "r1" and summary["placement"]["TeamMap"] == "r2"
    assert summary["exit_codes"] == {"laptop": 0, "r1": 0, "r2": 0, "r3": 0}
    sinks = {**summary["basestation"]["sinks"], **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    assert set(sinks) == {"Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3", "TeamMap"}
    assert all(s["received"] > 0 and s["duplicates_total"] == 0 for s in sinks.values())
    # one map per localisation step: each Loc output fanned out to its robot and to the map
    assert sinks["TeamMap"]["received"] >= min(sinks[c]["received"] for c in ("Loc-1", "Loc-2", "Loc-3")) - 2
    assert summary["robots"]["r2"]["counters"].get("flow-frames", 0) == 0  # r2 sends no flow: Loc-2 is not on r2
    for robot in ("r1", "r2", "r3"):
        assert not summary["robots"][robot]["errors"], (robot, summary["robots"][robot]["errors"])
        assert abs(summary["robots"][robot]["power_error"]) < 0.02  # the flows are metered as modelled
    assert summary["robots"]["r1"]["counters"]["flow-frames"] > 0  # r1 sent Loc-1's poses to r2

    replay = run_cli(["replay", summary["recording"], "--json"], env, timeout=120)
    assert replay.returncode == 0, replay.stderr[-3000:]
    data = json.loads(replay.stdout)
    assert data["lost_outputs"] == 0 and data["duplicated_outputs"] == 0
    assert data["outputs"]["chains"]["TeamMap"]["outputs"] > 0
    assert abs(data["energy_model_error_pct"]) <= 1.0  # the model charges each flow; so does the meter

    # stage and edge names in the recording: each flow's consumer gate, the map and its join
    rec = read_recording(summary["recording"])
    for producer in ("Loc-1", "Loc-2", "Loc-3"):
        _, consumed = rec.series(f"components/TeamMap/inputs/{producer}/consumed")
        assert consumed and consumed[-1] >= sinks["TeamMap"]["received"] - 2, producer
    paths = {str(c.entity_path) for c in RrdReader(summary["recording"]).stream().to_chunks()}
    assert {"/components/TeamMap/explored", "/components/TeamMap/poses", "/components/TeamMap/join",
            "/team/hosts/TeamMap"} <= paths
