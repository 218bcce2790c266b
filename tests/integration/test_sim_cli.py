"""`autopower sim` as a user runs it (the installed script, a process per run): one JSON object, the
same trace hash in processes with different string hashing, exit 3 for a violated invariant, and a
saved or shrunk run that replays the same."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.integration.test_json_contract import AUTOPOWER, check_keys

pytestmark = pytest.mark.parallel  # simulated runs of the installed command: no live team, no timed bound

SHORT = ["--mission", "30", "--quiet", "15"]


def sim(args: list[str], tmp_path: Path, hash_seed: str = "0", timeout: float = 120.0):
    env = {**os.environ, "PYTHONHASHSEED": hash_seed, "AUTOPOWER_STATE_DIR": str(tmp_path / "state")}
    result = subprocess.run([AUTOPOWER, "sim", *args], env=env, capture_output=True, text=True, timeout=timeout,
                            cwd=tmp_path)
    return result, json.loads(result.stdout)


def test_one_seed_gives_one_trace_whatever_the_string_hashing(tmp_path):
    args = ["paper-fig7", "--seed", "5", "--faults", "4", *SHORT, "--json"]
    (first, a), (second, b) = sim(args, tmp_path, "0"), sim(args, tmp_path, "1")
    assert first.returncode == second.returncode == 0, first.stderr
    check_keys("sim", a)
    assert a["ok"] and a["violations"] == [] and a["faults"]
    assert a["trace_sha256"] == b["trace_sha256"] and a["events"] == b["events"] > 1000
    assert {"produced", "delivered", "lost", "duplicated", "dropped_by_budget"} <= set(a["chains"]["Blob-2"])


def test_a_violated_invariant_exits_3_and_its_shrunk_schedule_replays(tmp_path):
    """A robot down past the end of the run: the team cannot end on the newest plan."""
    faults = [{"kind": "reorder", "t": 12.0, "duration": 2.0, "a": "r1", "b": "r3", "p": 0.01},
              {"kind": "crash", "t": 15.0, "duration": 100.0, "a": "r2"},
              {"kind": "migrate", "t": 18.0, "a": "Loc-1", "b": "r1"}]
    saved = tmp_path / "failing.json"
    saved.write_text(json.dumps({"autopower_sim": 1, "scenario": "paper-fig7", "seed": 1, "mission_s": 20,
                                 "quiet_s": 10, "faults": faults}))
    result, out = sim(["--replay", str(saved), "--shrink", "--save", "shrunk.json", "--json"], tmp_path)
    assert result.returncode == 3, result.stderr
    check_keys("sim", out)
    assert not out["ok"] and out["shrunk"]["invariant"] == out["violations"][0]["invariant"]
    assert any(v["invariant"] == "newest-plan" and "r2 is down at the end" in v["detail"] for v in out["violations"])
    assert [f["kind"] for f in out["shrunk"]["faults"]] == ["crash"] and out["shrunk"]["file"] == "shrunk.json"
    again, replayed = sim(["--replay", "shrunk.json", "--json"], tmp_path)
    assert again.returncode == 3 and replayed["faults"] == out["shrunk"]["faults"]
    assert replayed["violations"] == out["shrunk"]["violations"]


def test_a_saved_run_replays_with_the_same_trace(tmp_path):
    result, out = sim(["--seed", "7", "--faults", "3", *SHORT, "--save", "run.json", "--json"], tmp_path)
    assert result.returncode == 0 and out["saved"] == "run.json"
    again, replayed = sim(["--replay", "run.json", "--json"], tmp_path, hash_seed="3")
    assert again.returncode == 0 and replayed["trace_sha256"] == out["trace_sha256"]


@pytest.mark.parametrize("faults,message", [
    ([{"kind": "crash", "t": 15.0, "duration": 1.0, "a": "r9"}], "does not fit scenario paper-fig7"),
    ([{"kind": "earthquake", "t": 15.0}], "not a fault"),
])
def test_a_replay_file_that_does_not_fit_is_bad_input(tmp_path, faults, message):
    saved = tmp_path / "bad.json"
    saved.write_text(json.dumps({"autopower_sim": 1, "scenario": "paper-fig7", "seed": 1, "mission_s": 20,
                                 "quiet_s": 10, "faults": faults}))
    result, out = sim(["--replay", str(saved), "--json"], tmp_path)
    assert result.returncode == 2 and message in out["error"] and "Traceback" not in result.stderr
