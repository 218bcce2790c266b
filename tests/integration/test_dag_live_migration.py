"""A fan-in stage migrating live (docs/concepts/chains.md): TeamMap moves between real
agent processes on Zenoh while Loc-1..3 keep feeding it; every map comes once, in order, and no
input is missed, late or run twice across the moves (the join's state moves with the stage)."""

from __future__ import annotations

import time

from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.protocol import MigrateCommand
from tests.integration.runtime_helpers import errors_of, sinks_of, wait_for


def test_team_map_migrates_live_with_its_join(tmp_path):
    spec = TeamSpec(scenario="paper-teammap", speed=10.0, auto_replan=False, log_dir=tmp_path / "logs",
                    pins=("Loc-1=r1",))
    team = LocalTeam(spec, build_scenario("paper-teammap"))
    team.__enter__()
    try:
        team.wait_ready(60)
        before = team.snapshot()["migrations_done"]
        for node in ("r2", "r3", "laptop"):
            assert team.client.request(MigrateCommand(stage="TeamMap", to_node=node)).ok
            wait_for(team, lambda s, n=node: s["placement"]["TeamMap"] == n and s["ready"], 30, f"TeamMap on {node}")
            time.sleep(1.0)  # a few steps (2 s virtual each) on each host
        maps = sinks_of(team.snapshot())["TeamMap"]["contiguous"]
        snap = wait_for(team, lambda s: sinks_of(s)["TeamMap"]["contiguous"] >= maps + 5, 30, "more maps")
        assert snap["migrations_done"] >= before + 3
        sink = sinks_of(snap)["TeamMap"]
        assert sink["duplicates_total"] == 0 and sink["received"] == sink["contiguous"] == sink["max_seq"] + 1
        for node, errors in errors_of(snap).items():  # no join-missing/-late, duplicate-input, import-failed, ...
            assert not errors, (node, errors)
    finally:
        codes = team.stop()
        assert all(c == 0 for c in codes.values()), (codes, team.log_dir)
