"""Stage worker processes, live: real processes, real Zenoh, the base station with ``--stage-workers on``.

Both motion detectors of the worked example run on the base station, each in its own worker
process. Motion-2's detector spins for ever from its 10th frame: its worker is SIGKILLed, the
stage is reported failed, and Motion-1 (the same node, another worker) goes on, exactly once.
Then Motion-1 moves from the worker-hosting base station to a robot with its state (its outputs
stay those of a run that never moved).
"""

from __future__ import annotations

import os
import time


from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.cli.options import build_scenario
from autopower.protocol import MigrateCommand
from tests.integration.runtime_helpers import sinks_of, wait_for
from tests.integration.test_plugin_components import assert_exactly_once_and_like_offline, plugin_path, with_component  # noqa: F401

SPIN_AT_FRAME = 10


def children_of(pid: int) -> set[int]:
    out = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as f:
                    ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if ppid == pid:
                out.add(int(entry))
    return out


def test_a_spinning_component_is_killed_the_other_stage_runs_on_and_a_stage_moves_with_its_state(
        plugin_path, tmp_path):  # noqa: F811
    path = with_component(tmp_path, "Motion-2", "Spinner", "tests.integration.faulty_components:SpinsAtTen")
    spec = TeamSpec(scenario=str(path), speed=10.0, auto_replan=False, log_dir=tmp_path / "logs",
                    pins=("Motion-1=laptop", "Motion-2=laptop"), stage_workers="on")
    team = LocalTeam(spec, build_scenario(str(path)))
    team.__enter__()
    try:
        team.wait_ready(60)
        base_pid = team.children["laptop"].proc.pid
        wait_for(team, lambda s: len(children_of(base_pid)) == 1, 30, "the base station's worker zygote")
        [zygote] = children_of(base_pid)  # the worker factory: one per node
        wait_for(team, lambda s: len(children_of(zygote)) == 2 and sinks_of(s).get("Motion-1", {}).get(
            "contiguous", 0) >= 5, 30, "both stages running in workers")
        # the hang verdict for a call that keeps computing: 10 limits of 2 s (3 periods at x10 < 2 s)
        snap = wait_for(team, lambda s: "Motion-2" in s.get("failed_stages", {}), 60, "Motion-2 to be killed")
        failed = snap["failed_stages"]["Motion-2"]
        assert "hung" in failed and "still running" in failed and "its worker process was killed" in failed, failed
        assert "Motion-2" in snap["disabled"]
        assert sinks_of(snap)["Motion-2"]["contiguous"] == SPIN_AT_FRAME  # every frame before it, none after
        deadline = time.monotonic() + 10
        while len(children_of(zygote)) != 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(children_of(zygote)) == 1  # killed: only Motion-1's worker is left, nothing spins
        before = sinks_of(snap)["Motion-1"]["contiguous"]
        snap = wait_for(team, lambda s: sinks_of(s)["Motion-1"]["contiguous"] >= before + 20, 20, "Motion-1 to go on")
        assert team.children["laptop"].proc.poll() is None
        # Motion-1 leaves the worker-hosting base station for r1, with its state (the previous frame)
        assert team.client.request(MigrateCommand(stage="Motion-1", to_node="r1")).ok
        wait_for(team, lambda s: s["placement"]["Motion-1"] == "r1" and s["ready"], 20, "Motion-1 on r1")
        moved = sinks_of(team.snapshot())["Motion-1"]["contiguous"]
        snap = wait_for(team, lambda s: sinks_of(s)["Motion-1"]["contiguous"] >= moved + 20, 30, "Motion-1 on r1")
        assert sinks_of(snap)["Motion-1"]["duplicates_total"] == 0
        assert_exactly_once_and_like_offline(team.scenario, {**snap, "basestation": {
            "sinks": {"Motion-1": sinks_of(snap)["Motion-1"]}}, "robots": {}})
        assert len(children_of(zygote)) == 0  # its worker went with it
    finally:
        codes = team.stop()
        assert all(c == 0 for c in codes.values()), (codes, team.log_dir)
