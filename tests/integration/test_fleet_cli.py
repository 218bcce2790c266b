"""`autopower scenarios fleet` as a user runs it: the installed script writes a fleet, `check` accepts
it and `plan` places every stage of it; bad input is one line on stderr and exit 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.test_json_contract import check_keys

pytestmark = pytest.mark.parallel  # commands that start no team: no live process to share the cores with (tests/conftest.py)

AUTOPOWER = str(Path(sys.executable).with_name("autopower"))
ENV = {**os.environ, "RERUN_ANALYTICS": "0"}


def run(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run([AUTOPOWER, *args], env=ENV, capture_output=True, text=True, timeout=timeout)


def test_a_30_robot_fleet_is_written_checked_and_planned(tmp_path):
    path = tmp_path / "fleet-30.toml"
    made = run("scenarios", "fleet", "30", "--out", str(path), "--json")
    assert made.returncode == 0, made.stderr
    summary = json.loads(made.stdout)
    check_keys("scenarios fleet", summary)
    assert summary == {"path": str(path), "scenario": "fleet-30", "robots": 30, "cameras": 30, "chains": 60,
                       "stages": 60, "topology": "fully-connected", "links": 30 + 30 * 29 // 2,
                       "media": {"laptop-robot": ["802.11a", "gsm"], "robot-robot": ["802.11a", "bluetooth"]}}
    checked = run("check", str(path))
    assert checked.returncode == 0, checked.stderr
    assert "fleet-30 — 30 robots, 60 chains, 60 stages" in " ".join(checked.stdout.split())
    # The time-sharing bound's column generation takes over a minute at 30 robots (see
    # docs/getting-started.md); the 8-robot plan below runs it, with the same JSON.
    planned = run("plan", str(path), "--json", "--no-bound")
    assert planned.returncode == 0, planned.stderr
    plan = json.loads(planned.stdout)
    check_keys("plan", plan)
    stages = {f"{kind}-{i}" for kind in ("Loc", "Blob") for i in range(1, 31)}
    assert set(plan["allocation"]) == stages and plan["dropped_chains"] == {}
    assert set(plan["allocation"].values()) <= {f"r{i}" for i in range(1, 31)} | {"laptop"}
    assert plan["proven_optimal"] and plan["lifetime_s"] > 0


def test_a_relay_fleet_with_a_few_cameras_plans_with_its_bound(tmp_path):
    path = tmp_path / "fleet-8.toml"
    made = run("scenarios", "fleet", "8", "--cameras", "3", "--topology", "relay", "--medium", "802.11a",
               "--seed", "5", "--out", str(path))
    assert made.returncode == 0, made.stderr
    assert "fleet-8 — 8 robots (3 with a camera), 11 chains, 11 stages, relay" in " ".join(made.stdout.split())
    planned = run("plan", str(path), "--json")  # with the time-sharing bound (column generation here)
    assert planned.returncode == 0, planned.stderr
    plan = json.loads(planned.stdout)
    check_keys("plan", plan)
    assert len(plan["allocation"]) == 11 and plan["time_sharing_bound"]["method"] == "column generation"
    assert isinstance(plan["time_sharing_bound"]["proven"], bool)


def test_without_out_stdout_is_the_toml_alone(tmp_path):
    printed = run("scenarios", "fleet", "2")
    assert printed.returncode == 0 and printed.stderr == ""
    path = tmp_path / "printed.toml"
    path.write_text(printed.stdout)
    assert run("check", str(path)).returncode == 0


@pytest.mark.parametrize("args,message", [
    (["0"], "N must be >= 1"),
    (["3", "--cameras", "4"], "--cameras must be between 0 and the number of robots (3)"),
    (["3", "--medium", "wifi"], "unknown medium 'wifi'"),
    (["3", "--topology", "star"], "Invalid value for '--topology'"),
    (["3", "--json"], "give --out FILE"),
])
def test_bad_input_is_one_line_on_stderr_and_exit_2(tmp_path, args, message):
    out = tmp_path / "never.toml"
    result = run("scenarios", "fleet", *args, *([] if "--json" in args else ["--out", str(out)]))
    assert result.returncode == 2, (result.stdout, result.stderr)
    line, = result.stderr.splitlines()
    assert line.startswith("error: ") and message in line
    assert not out.exists()
