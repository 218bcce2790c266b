"""A team whose processes exited with errors says which, with what code, and how each one's log
ends: a base station killed for not stopping in time must leave its reason where the user looks."""

from __future__ import annotations

from autopower.launch.localhost import Child, LocalTeam, TeamSpec
from autopower.model.loading import load_scenario


def test_the_error_names_each_bad_child_with_the_end_of_its_log(tmp_path, monkeypatch):
    monkeypatch.setenv("AUTOPOWER_STATE_DIR", str(tmp_path / "state"))
    team = LocalTeam(TeamSpec(scenario="paper-fig7", secure=False, log_dir=tmp_path / "logs"),
                     load_scenario("paper-fig7"))
    laptop_log = tmp_path / "logs" / "laptop.log"
    laptop_log.write_text("".join(f"line {i}\n" for i in range(20)) + "base station stopping: SIGTERM\n")
    team.children = {"laptop": Child("laptop", proc=None, log_path=laptop_log),
                     "r1": Child("r1", proc=None, log_path=tmp_path / "logs" / "r1.log")}  # r1 wrote nothing
    report = team.exit_report({"laptop": -9, "r1": 1}, lines=3)
    lines = report.splitlines()
    assert lines[0] == f"process(es) exited with errors: {{'laptop': -9, 'r1': 1}}; logs in {tmp_path / 'logs'}"
    assert lines[1:] == ["laptop's log ends:", "line 18", "line 19", "base station stopping: SIGTERM"]
