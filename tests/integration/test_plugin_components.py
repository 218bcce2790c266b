"""A component of one's own, live: the worked example (examples/motion_demo) between real processes.

Its scenario names the plug-in by import path; every process imports it for itself (the children
find it on PYTHONPATH, as after `pip install ./examples/motion_demo`). The planner places it, it
migrates between agents carrying its state (the previous frame), each output reaches the sink
exactly once, and the batteries drain as the model says. A second team runs a detector that
raises mid-run: its stage stops, its agent and the other chain do not.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from autopower.chains.registry import component_types, unregister_component_type
from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.model.energy import evaluate
from autopower.model.network import build_network
from autopower.planner import PlanRequest, plan
from autopower.protocol import MigrateCommand
from tests.integration.runtime_helpers import (
    errors_of,
    measured_power,
    reference_digest,
    settled,
    sinks_of,
    sources_of,
    wait_for,
)

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "motion_demo"
SCENARIO = EXAMPLE / "motion.toml"
SPEED = 10.0
ROBOTS = ("r1", "r2")


@pytest.fixture(scope="module")
def plugin_path():
    """The example package importable here and in every child process (PYTHONPATH); the component
    types this module registers in this process are unregistered after it (other tests' registry)."""
    before = os.environ.get("PYTHONPATH")
    types = set(component_types())
    os.environ["PYTHONPATH"] = os.pathsep.join([str(EXAMPLE), str(REPO)] + ([before] if before else []))
    sys.path.insert(0, str(EXAMPLE))
    try:
        yield
    finally:
        for name in set(component_types()) - types:
            unregister_component_type(name)
        sys.path.remove(str(EXAMPLE))
        if before is None:
            del os.environ["PYTHONPATH"]
        else:
            os.environ["PYTHONPATH"] = before


def start(path: Path, log_dir: Path, **spec_kwargs) -> LocalTeam:
    spec = TeamSpec(scenario=str(path), speed=SPEED, auto_replan=False, log_dir=log_dir, **spec_kwargs)
    team = LocalTeam(spec, build_scenario(str(path)))  # imports and registers the plug-in here too
    team.__enter__()
    return team


@pytest.fixture(scope="module")
def team(plugin_path, tmp_path_factory):
    team = start(SCENARIO, tmp_path_factory.mktemp("motion"))
    try:
        team.wait_ready(60)
        yield team
    finally:
        codes = team.stop()
        assert all(c == 0 for c in codes.values()), (codes, team.log_dir)


def assert_exactly_once_and_like_offline(scenario, snap) -> None:
    for chain, stats in sinks_of(snap).items():
        assert stats["duplicates_total"] == 0, chain
        # each output carries the CRC of the frame the detector compared against (its state):
        # equal to a run that never moved means the state crossed every move byte for byte
        assert stats["digest"] == reference_digest(scenario, chain, stats["contiguous"]), chain


def test_the_planner_places_the_plugin(team):
    best = plan(PlanRequest(scenario=team.scenario))
    snap = wait_for(team, lambda s: len(sinks_of(s)) == 2 and all(v["received"] >= 8 for v in sinks_of(s).values()),
                    30, "results from both motion detectors")
    assert snap["placement"] == best.allocation
    assert set(snap["basestation"]["hosted"].values()) == {"running"}
    assert not any(e for errs in errors_of(snap).values() for e in errs if e != "garbled")
    assert_exactly_once_and_like_offline(team.scenario, snap)


def test_it_migrates_between_agents_with_its_state(team):
    client = team.client
    before = team.snapshot()["migrations_done"]
    for node in ("r1", "r2", "laptop", "r2"):
        assert client.request(MigrateCommand(stage="Motion-2", to_node=node)).ok
        wait_for(team, lambda s, n=node: s["placement"]["Motion-2"] == n and s["ready"], 20, f"Motion-2 on {node}")
        time.sleep(0.5)  # a few frames on each host
    snap = wait_for(team, lambda s: sinks_of(s)["Motion-2"]["contiguous"] >= 40, 30, "Motion-2 results")
    assert snap["migrations_done"] >= before + 4
    assert_exactly_once_and_like_offline(team.scenario, snap)


def test_metered_energy_matches_the_model_within_1_percent(team):
    scenario, client = team.scenario, team.client
    for allocation in ({"Motion-1": "laptop", "Motion-2": "laptop"}, {"Motion-1": "r1", "Motion-2": "r2"}):
        for stage, node in allocation.items():
            assert client.request(MigrateCommand(stage=stage, to_node=node)).ok
        s1 = wait_for(team, lambda s: settled(s) and s["placement"] == allocation, 30, "the allocation to settle")  # noqa: B023 (called in this iteration)
        time.sleep(10.0)  # the measurement window (100 s virtual)
        s2 = team.snapshot()
        assert s2["epoch"] == s1["epoch"], "the placement changed during the measurement"
        ev = evaluate(scenario, build_network(scenario, media=s2["media"]), s2["placement"])
        for robot in ROBOTS:
            assert measured_power(s1, s2, robot) == pytest.approx(ev.robots[robot].total_w, rel=0.01), \
                (robot, allocation)
        # metering charges what really ran: a machine too loaded for the speed would miss periods
        # and fall short of the model; make sure that is not what the comparison above measured
        missed = sum(s["missed"] for s in sources_of(s2).values()) - sum(s["missed"] for s in sources_of(s1).values())
        produced = sum(s["produced_total"] for s in sources_of(s2).values()) - sum(
            s["produced_total"] for s in sources_of(s1).values())
        assert produced > 300 and missed <= 0.05 * produced, (
            f"{missed} of {produced} periods missed under {allocation}: a node's loop stalled; its log says "
            f"when: {late_log_lines(team.log_dir)}")
    assert_exactly_once_and_like_offline(scenario, team.snapshot())


def late_log_lines(log_dir: Path) -> list[str]:
    """The nodes' log lines that say a source skipped periods (when and for how long a loop stalled)."""
    return [f"{log.stem}: {line.strip()}" for log in sorted(Path(log_dir).glob("*.log"))
            for line in log.read_text(errors="replace").splitlines() if "late; skipped" in line][-20:]


def with_component(tmp_path: Path, chain: str, name: str, implementation: str) -> Path:
    """The example scenario with ``chain`` run by plug-in class ``implementation`` (as component
    ``name``, same sizes and latencies as Motion), written to ``tmp_path``."""
    motion = f'[[chains]]\nname = "{chain}"\nsource = "r{chain[-1]}"\nsink = "operator"\ncomponent = "Motion"'
    text = SCENARIO.read_text()
    assert motion in text, f"{chain} is not a Motion chain of {SCENARIO}"
    text = text.replace(motion, motion.replace('component = "Motion"', f'component = "{name}"'))
    text = text.replace("state_bytes = { Motion = 3076 }", f"state_bytes = {{ Motion = 3076, {name} = 3076 }}")
    text += f'''
[components.{name}]
implementation = "{implementation}"
source = "motion_demo.camera:GreyCamera"
latency_s = {{ laptop = 0.0005, sitsang = 0.025 }}
'''
    path = tmp_path / f"{name.lower()}.toml"
    path.write_text(text)
    return path


def test_a_component_that_raises_stops_its_stage_not_its_agent(plugin_path, tmp_path):
    # Motion-2 gets a detector that raises at its 10th frame; Motion-1 keeps the good one
    path = with_component(tmp_path, "Motion-2", "Flaky", "tests.integration.faulty_components:RaisesAtTen")
    team = start(path, tmp_path / "logs", pins=("Motion-2=r2",))
    try:
        team.wait_ready(60)
        snap = wait_for(team, lambda s: "Motion-2" in s.get("failed_stages", {}), 30, "Motion-2 to fail")
        assert "RaisesAtTen: frame 10 is the end of the world" in snap["failed_stages"]["Motion-2"]
        assert "Motion-2" in snap["disabled"]
        status = wait_for(team, lambda s: "Motion-2" in s["robots"]["r2"]["status"]["failed"], 10,
                          "r2's status to report it")["robots"]["r2"]["status"]
        assert status["failed"]["Motion-2"] == "raised: run(seq 10): ValueError: RaisesAtTen: frame 10 is the end of the world"
        done = sinks_of(snap)["Motion-2"]["contiguous"]
        assert done == 10  # every frame before the failure, none after
        produced = sinks_of(snap)["Motion-1"]["contiguous"]
        later = wait_for(team, lambda s: sinks_of(s)["Motion-1"]["contiguous"] >= produced + 10, 20,
                         "Motion-1 to go on")
        team.check_children()  # r2's agent is alive
        assert later["robots"]["r2"]["present"]
        assert_exactly_once_and_like_offline(team.scenario, {**later, "basestation": {
            "sinks": {"Motion-1": sinks_of(later)["Motion-1"]}}, "robots": {}})
    finally:
        assert all(c == 0 for c in team.stop().values())
