"""Real, silent faults on a real team: link cuts through the link proxies, SIGKILL, SIGSTOP.

One team of processes (base station + three agents, every link through its own LinkProxy,
lease 500 ms) takes a sequence of faults; after each one the base station's own record says
when it noticed and when the team ran the new plan. Bounded: one team, five faults, every wait
has a deadline.
"""

from __future__ import annotations

import time

import pytest

from autopower.cli.options import build_scenario
from autopower.launch.faults import FaultController
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.launch.summary import lost_outputs, missed_while_stopped, status_line, team_sinks
from tests.integration.runtime_helpers import wait_for

DETECT_S = 1.0
RECONFIGURE_S = 1.5


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=5.0, lease_ms=500, proxied_links=True,
                    log_dir=tmp_path_factory.mktemp("faults"))
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        yield team


def _fault(team, controller, request, kind, target):
    before = len(team.snapshot()["faults"])
    t0 = controller.apply(request)["fault"]["t_unix"]
    snap = wait_for(team, lambda s: any(f["kind"] == kind and f["target"] == target and f["reconfigured_unix"]
                                        for f in s["faults"][before:]), 10, f"{kind} {target} handled")
    fault = next(f for f in snap["faults"][before:] if f["kind"] == kind and f["target"] == target)
    return snap, fault["detected_unix"] - t0, fault["reconfigured_unix"] - t0


def _missing_outputs(snap) -> int:
    return lost_outputs(team_sinks(snap))


def test_cut_heal_kill_freeze(team):
    controller = FaultController(team)
    placement = team.snapshot()["placement"]

    # a silent cut of r1's link to the base station: r1 stays in the team through another robot
    snap, detected, reconfigured = _fault(team, controller, {"op": "cut", "a": "r1", "b": "laptop"},
                                          "link-down", "laptop-r1")
    assert detected <= DETECT_S and reconfigured <= RECONFIGURE_S, (detected, reconfigured)
    assert snap["robots"]["r1"]["present"]
    assert ["laptop", "r1"] in snap["links_down"]
    # r1's status and acknowledgements still reach the base station (relayed by r2 or r3)
    wait_for(team, lambda s: s["robots"]["r1"]["status"]["plan_epoch"] == s["epoch"] and s["ready"], 5,
             "r1 on the new plan through a relay")

    # heal: the link is used again only after it stayed up (hysteresis), placement as before
    controller.apply({"op": "heal", "a": "r1", "b": "laptop"})
    snap = wait_for(team, lambda s: not s["links_down"] and s["ready"], 10, "the healed link back in the plan")
    assert snap["placement"] == placement
    assert any("is back" in e for e in snap["events"])
    # what was in flight into the dead link was resent from custody: no sink misses an output
    snap = wait_for(team, lambda s: _missing_outputs(s) == 0, 10, "every output of the cut delivered")
    assert all(st["duplicates_total"] == 0 for st in team_sinks(snap))

    # SIGKILL: the socket closes, the others say so at once
    snap, detected, reconfigured = _fault(team, controller, {"op": "kill", "robot": "r2"}, "node-left", "r2")
    assert detected <= DETECT_S and reconfigured <= RECONFIGURE_S, (detected, reconfigured)
    assert not snap["robots"]["r2"]["present"]
    assert "r2" not in snap["placement"].values()

    # SIGSTOP: only the lease notices
    t_frozen = time.time()
    snap, detected, reconfigured = _fault(team, controller, {"op": "freeze", "robot": "r3"}, "node-left", "r3")
    assert detected <= DETECT_S and reconfigured <= RECONFIGURE_S, (detected, reconfigured)
    assert snap["robots"]["r1"]["present"]
    time.sleep(max(0.0, 2.0 - (time.time() - t_frozen)))  # stopped for 2 s at least: 40 camera periods at x5
    controller.apply({"op": "thaw", "robot": "r3"})
    wait_for(team, lambda s: s["robots"]["r3"]["present"], 10, "r3 back after thaw")
    # what r3 found missed when it came back is counted as missed while stopped, not as too fast a speed-up
    snap = wait_for(team, lambda s: missed_while_stopped(s) > 0, 10, "r3's periods missed while stopped reported")
    blob = snap["robots"]["r3"]["status"]["sources"]["Blob-3"]
    assert 0 < blob["missed_stopped"] <= blob["missed"]
    assert "of them while an agent was stopped" in status_line(snap, 5.0)


def test_bad_fault_requests_are_refused_clearly(team):
    from autopower.errors import AutoPowerError

    controller = FaultController(team)
    with pytest.raises(AutoPowerError, match="unknown robot 'r9'"):
        controller.apply({"op": "kill", "robot": "r9"})
    with pytest.raises(AutoPowerError, match="unknown node 'r7'"):
        controller.apply({"op": "cut", "a": "r7", "b": "laptop"})


def test_subgroup_reallocates_without_the_base_station(tmp_path):
    """Every robot cut from the base station: the robots agree among themselves (2PC), keep
    running their chains, and the base station adopts what they run when the links return."""
    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=5.0, lease_ms=500, proxied_links=True, log_dir=tmp_path)
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        controller = FaultController(team)
        robots = ["r1", "r2", "r3"]
        for r in robots:
            controller.apply({"op": "cut", "a": r, "b": "laptop"})
        t_cut = time.time()

        def committed() -> bool:
            text = "".join((tmp_path / f"{r}.log").read_text() for r in robots)
            return text.count("subgroup round") >= 3 and "committed" in text
        end = time.monotonic() + 10
        while not committed() and time.monotonic() < end:
            time.sleep(0.1)
        assert committed(), "no subgroup round committed within 10 s of cutting every robot from the base"
        assert time.time() - t_cut < 10
        leader_log = (tmp_path / "r1.log").read_text()
        assert "subgroup:" in leader_log  # the decision is explained in the log

        time.sleep(1.0)  # the subgroup runs on its own for a while
        for r in robots:
            controller.apply({"op": "heal", "a": r, "b": "laptop"})
        # A robot is "present" again as soon as its liveliness returns, before its first fresh
        # status arrives: wait (bounded) for statuses that report the commit, not just presence.
        snap = wait_for(team, lambda s: s["ready"] and all(v["present"] for v in s["robots"].values())
                        and not s["links_down"]
                        and all((s["robots"][r].get("status") or {}).get("counters", {}).get("subgroup-commits", 0) >= 1
                                for r in robots), 20, "the team back under the base station, reporting the commit")
        assert snap["adopted"] >= 1  # it started from what the robots actually ran
        for r in robots:
            counters = snap["robots"][r]["status"]["counters"]
            assert counters.get("subgroup-commits", 0) >= 1, (r, counters)
        assert snap["robots"]["r1"]["status"]["counters"].get("subgroup-agreement-us", 0) > 0
        sinks = {**snap["basestation"]["sinks"]}
        for info in snap["robots"].values():
            sinks.update(info["status"]["sinks"])
        assert all(s["duplicates_total"] == 0 for s in sinks.values()), sinks  # nothing ran twice

