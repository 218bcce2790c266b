"""A live fleet beyond the paper's trio: `autopower up` on a generated 10-robot team, every robot
with a camera (a Loc and a 4 Hz Blob chain each), as a user runs it: the installed CLI, real
processes, real Zenoh sessions through the link proxies.

Bounded: one team, a fixed wall duration, and `up` stops every process itself.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

AUTOPOWER = os.environ.get("AUTOPOWER_BIN") or str(Path(sys.executable).parent / "autopower")
ROBOTS = 10


@pytest.mark.slow
def test_a_ten_robot_fleet_with_cameras_runs_every_chain_gap_free_and_stops_cleanly(tmp_path):
    env = {**os.environ, "AUTOPOWER_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}
    scenario = tmp_path / "fleet.toml"
    made = subprocess.run([AUTOPOWER, "scenarios", "fleet", str(ROBOTS), "--out", str(scenario), "--json"], env=env,
                          capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    chains = json.loads(made.stdout)["chains"]
    result = subprocess.run([AUTOPOWER, "up", str(scenario), "--speed", "1", "--duration", "20", "--json",
                             "--log-dir", str(tmp_path / "logs")], env=env, capture_output=True, text=True,
                            timeout=240)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["ready"] and summary["ready_after_s"] < 30.0, summary.get("ready_after_s")
    assert summary["exit_codes"] == {**{f"r{i}": 0 for i in range(1, ROBOTS + 1)}, "laptop": 0}  # nothing killed
    assert summary["missed_ratio"] < 0.05  # startup included, on a 2-core machine running 11 processes
    sinks = {**summary["basestation"]["sinks"], **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    assert len(sinks) == chains == 2 * ROBOTS
    for chain, sink in sinks.items():
        # every output of its run so far, once: no gap below the highest, no second copy
        assert sink["received"] > 0 and sink["contiguous"] == sink["max_seq"] + 1, (chain, sink)
        assert sink["duplicates_total"] == 0, (chain, sink)
    for robot, info in summary["robots"].items():
        assert abs(info["power_error"]) < 0.02, (robot, info["mean_power_w"], info["predicted_w"])


@pytest.mark.slow
def test_a_twenty_robot_fleet_on_its_neighbours_links_is_ready_within_ten_seconds_and_misses_nothing(tmp_path):
    # every robot links to the base station and its two ring neighbours on either side: each
    # process opens at most 5 connections, not 20 (a full mesh of 21 processes is 210 links)
    robots = 20
    env = {**os.environ, "AUTOPOWER_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}
    scenario = tmp_path / "ring.toml"
    made = subprocess.run([AUTOPOWER, "scenarios", "fleet", str(robots), "--topology", "neighbours", "--neighbours",
                           "2", "--out", str(scenario), "--json"], env=env, capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    assert json.loads(made.stdout)["links"] == robots + 2 * robots
    result = subprocess.run([AUTOPOWER, "up", str(scenario), "--speed", "1", "--duration", "20", "--json",
                             "--log-dir", str(tmp_path / "logs")], env=env, capture_output=True, text=True,
                            timeout=240)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["ready"] and summary["ready_after_s"] <= 10.0, summary.get("ready_after_s")
    assert summary["exit_codes"] == {**{f"r{i}": 0 for i in range(1, robots + 1)}, "laptop": 0}
    assert summary["periods_missed"] == 0, summary["missed_periods_pct"]
    assert not summary["basestation"]["errors"], summary["basestation"]["errors"]  # no queue drops, no garbage
    sinks = {**summary["basestation"]["sinks"], **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    assert len(sinks) == 2 * robots
    for chain, sink in sinks.items():
        assert sink["received"] > 0 and sink["contiguous"] == sink["max_seq"] + 1, (chain, sink)
        assert sink["duplicates_total"] == 0, (chain, sink)
    for robot, info in summary["robots"].items():
        assert abs(info["power_error"]) < 0.01, (robot, info["mean_power_w"], info["predicted_w"])
    # the sessions ran over exactly those links, each of them used
    links = summary["link_bytes"]
    assert len(links) == robots + 2 * robots and all(n > 0 for n in links.values()), links
    assert all(sum(robot in pair.split("-") for pair in links) == 5 for robot in summary["robots"])
