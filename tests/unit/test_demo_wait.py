"""The demo's last step ends when a robot runs dry, even if no base station is up to see it.

On a loaded machine (load 14–31 on 2 cores) the demo's robots ran dry while the base station the
story had just killed was still starting (3.6–18 s to come up): the new one never heard of it and
the demo failed with "timed out waiting for the first robot to run dry". A robot that runs dry
leaves with status 0; the demo now takes that as the end and the recording says when.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from autopower.errors import AutoPowerError
from autopower.launch.demo import _wait
from autopower.launch.localhost import Child, LocalTeam, TeamSpec
from autopower.model.loading import load_scenario


class BaseStationDown:
    """A team whose base station does not answer (killed, its successor still starting)."""

    log_dir = "/nowhere"

    def __init__(self, gone: set[str]):
        self.gone, self.asked = gone, 0

    def check_children(self):
        return []

    def snapshot(self, timeout_s: float = 5.0) -> dict:
        self.asked += 1
        raise AutoPowerError("the base station did not answer")


def test_the_last_wait_ends_when_a_robot_has_left_though_no_base_station_answers():
    team = BaseStationDown({"r3"})
    snap = _wait(team, lambda s: bool(s.get("first_depletion")), 5.0, "the first robot to run dry",
                 unless=lambda: bool(team.gone & {"r1", "r2", "r3"}))
    assert snap == {} and team.asked == 1  # at once, not after 5 s


def test_without_a_robot_gone_it_still_times_out_with_the_reason():
    team = BaseStationDown(set())
    with pytest.raises(AutoPowerError, match="timed out after 0.3 s waiting for the first robot to run dry"):
        _wait(team, lambda s: bool(s.get("first_depletion")), 0.3, "the first robot to run dry",
              unless=lambda: bool(team.gone))


def test_a_team_knows_which_children_left_on_their_own(tmp_path):
    team = LocalTeam(TeamSpec(scenario="paper-fig7", log_dir=str(tmp_path)), load_scenario("paper-fig7"))
    runs = {name: subprocess.Popen([sys.executable, "-c", code]) for name, code in
            (("r1", "import time; time.sleep(30)"), ("r2", "raise SystemExit(0)"), ("r3", "raise SystemExit(3)"),
             ("laptop", "raise SystemExit(0)"))}
    try:
        for name, proc in runs.items():
            team.children[name] = Child(name, proc, tmp_path / f"{name}.log")
        for name in ("r2", "r3", "laptop"):
            runs[name].wait(10)
        team.expected_exits.add("laptop")  # killed or stopped by the demo on purpose: not "left"
        assert team.exited_cleanly() == {"r2"}  # r1 runs, r3 crashed
    finally:
        runs["r1"].kill()
        runs["r1"].wait()
