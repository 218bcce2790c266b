"""The control plane in the model and the planner: statuses and keep-alives charged on every link."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from autopower.errors import ScenarioError
from autopower.model.control_plane import ControlPlaneSpec
from autopower.model.energy import evaluate
from autopower.model.loading import ScenarioParser, load_scenario, load_toml, resolve_scenario_path
from autopower.model.network import build_network, media_choices
from autopower.planner import PlanRequest, plan

ALL_LAPTOP = {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "laptop", "Blob-3": "laptop"}


def charged(scenario, **shape):
    return dataclasses.replace(scenario, control_plane=ControlPlaneSpec(enabled=True, **shape))


def test_off_by_default_so_the_papers_figures_stay_exact():
    fig7 = load_scenario("paper-fig7")
    assert not fig7.control_plane.enabled
    ev = evaluate(fig7, build_network(fig7), ALL_LAPTOP)
    assert all(rp.control_w == 0.0 for rp in ev.robots.values())


def test_a_robots_control_power_is_the_rules_worked_by_hand():
    """r1 on 802.11a with three links (laptop, r2, r3), a status every 2 s (the heartbeat of a
    steady team), a 0.5 s lease with two keep-alives per lease: per second on each link half a
    status and 3.5 keep-alives (the four quarter seconds, one in eight of which carries a status),
    each in a packet of 74 bytes more, each answered by a 52-byte acknowledgement. Its status to the
    laptop goes whole every fifth heartbeat (10 s) and as its change between."""
    fig7 = load_scenario("paper-fig7")
    network = build_network(fig7, media={"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    without = evaluate(fig7, network, ALL_LAPTOP).robots["r1"]
    with_cp = evaluate(charged(fig7), network, ALL_LAPTOP).robots["r1"]
    keep_alives = 3.5 * (8 + 74)
    to_laptop = (800 + 4 * 250) / 5
    sent = (0.5 * (to_laptop + 74) + keep_alives + 4 * 52) + 2 * (0.5 * (150 + 74) + keep_alives + 4 * 52)
    received = 3 * (0.5 * (150 + 74) + keep_alives + 4 * 52)  # the laptop sends robots the short status
    radio = fig7.radios["802.11a"]
    seconds_per_byte = 8 / (radio.kbps * 1024)
    expected_w = (sent * seconds_per_byte * (radio.send_w - radio.sleep_w)
                  + received * seconds_per_byte * (radio.receive_w - radio.sleep_w))
    assert with_cp.control_w == pytest.approx(expected_w, rel=1e-12)
    assert with_cp.total_w - without.total_w == pytest.approx(expected_w, rel=1e-9)


@pytest.mark.parametrize("topology", ["fully-connected", "relay"])
def test_the_milp_and_the_exhaustive_search_agree_with_the_control_plane_charged(topology):
    fig7 = charged(load_scenario("paper-fig7"))
    for media in media_choices(fig7, topology):
        network = build_network(fig7, topology, media)
        best = plan(PlanRequest(scenario=fig7, network=network, method="exhaustive")).evaluation.lifetime_s
        milp = plan(PlanRequest(scenario=fig7, network=network, method="milp")).evaluation.lifetime_s
        assert milp == pytest.approx(best, rel=1e-9), media
    chosen = plan(PlanRequest(scenario=fig7, topology=topology, method="milp"))
    assert chosen.evaluation.lifetime_s == pytest.approx(
        plan(PlanRequest(scenario=fig7, topology=topology, method="exhaustive")).evaluation.lifetime_s, rel=1e-9)


def test_over_gsm_the_relayed_statuses_cost_the_relay_most_of_its_lead():
    """The paper's GSM uplink. Without the control plane, relaying through r1 (one GSM session)
    outlives the full mesh (three) by 7 %. Counted, r1 also carries r2's and r3's statuses to the
    laptop over its GSM link, signed, at each heartbeat: sent whole every time, they made the relay
    die first; as their change from a whole one sent every 10 s (`protocol.statuses`), the relay
    keeps a lead under 1 %, r1 still its bottleneck."""
    fig7 = load_scenario("paper-fig7")
    media = {"laptop-robot": "gsm", "robot-robot": "802.11a"}

    def best(scenario, topology):
        return plan(PlanRequest(scenario=scenario, network=build_network(scenario, topology, media))).evaluation

    assert best(fig7, "relay").lifetime_s > 1.05 * best(fig7, "fully-connected").lifetime_s
    on = charged(fig7)
    full, relay = best(on, "fully-connected"), best(on, "relay")
    assert full.lifetime_s < relay.lifetime_s < 1.01 * full.lifetime_s
    assert relay.bottleneck == "r1"
    whole = charged(fig7, status_change_bytes=on.control_plane.status_bytes)
    assert best(whole, "fully-connected").lifetime_s > best(whole, "relay").lifetime_s


def test_the_longest_lease_within_the_detection_requirement_is_chosen():
    assert ControlPlaneSpec.lease_for(3.0) == 2.0
    assert ControlPlaneSpec.lease_for(0.5) == 0.5
    with pytest.raises(ScenarioError, match="shorter than the shortest lease"):
        ControlPlaneSpec.lease_for(0.2)
    fig7 = load_scenario("paper-fig7")
    network = build_network(fig7, media={"laptop-robot": "gsm", "robot-robot": "802.11a"})
    blobs_local = {**ALL_LAPTOP, "Blob-2": "r2", "Blob-3": "r3"}  # images do not fit on GSM
    strict = evaluate(charged(fig7, lease_s=0.5), network, blobs_local).lifetime_s
    relaxed = evaluate(charged(fig7, lease_s=2.0), network, blobs_local).lifetime_s
    assert relaxed > strict


def with_section(section: str) -> dict:
    where, text = resolve_scenario_path("paper-fig7")
    return load_toml(text + "\n[control_plane]\n" + section + "\n", where)


def test_the_scenario_file_sets_it_and_bad_values_get_a_clear_error():
    spec = ScenarioParser(with_section("enabled = true\nmax_detection_s = 3.0"), "", "fig7.toml").scenario().control_plane
    assert spec.enabled and spec.lease_s == 2.0 and spec.max_detection_s == 3.0
    for section, said in [
        ('enabled = "yes"', "control_plane.enabled: found 'yes'; expected true or false"),
        ("lease_s = 5.0\nmax_detection_s = 2.0", "lease_s 5 is longer than max_detection_s 2"),
        ("max_detection_s = 0.2", "control_plane.max_detection_s"),
        ("status_period_s = 0", "control_plane.status_period_s: found 0; expected a number > 0"),
        ("statuses = 3", "control_plane.statuses: unknown key"),
    ]:
        with pytest.raises(ScenarioError) as err:
            ScenarioParser(with_section(section), "", "fig7.toml").scenario()
        assert said in str(err.value) and "fig7.toml" in str(err.value), str(err.value)


def test_plan_on_the_command_line_charges_it_when_asked():
    autopower = str(Path(sys.executable).parent / "autopower")

    def run(*flags):
        done = subprocess.run([autopower, "plan", "paper-fig7", "--no-bound", "--json", *flags],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    off, on = run(), run("--control-plane")
    assert on["lifetime_s"] < off["lifetime_s"]
    assert all(r["control_w"] > 0 for r in on["evaluation"]["robots"].values())
    assert all(r["control_w"] == 0 for r in off["evaluation"]["robots"].values())


def test_a_team_whose_scenario_charges_it_plans_with_it_and_meters_against_the_rest():
    """The base station plans with the control plane its scenario charges (the plan's lifetime is
    the planner's); the power each robot is told to expect, which its meter's steady state is
    checked against, leaves it out, as the meter counts the control plane it measures apart."""
    from tests.unit.sim_team import SimTeam

    on = charged(load_scenario("paper-fig7"))
    expected = plan(PlanRequest(scenario=on)).evaluation
    team = SimTeam(on)
    team.join()
    team.run_exchanging_statuses(10.0)
    coordinator = team.coordinator
    assert coordinator.prediction.predicted_lifetime_s == pytest.approx(expected.lifetime_s, rel=1e-9)
    for robot, rp in expected.robots.items():
        told = team.nodes[robot].plan.predicted_w[robot]
        assert rp.control_w > 0 and told == pytest.approx(rp.steady_w, rel=1e-9)


def test_evaluate_shows_the_control_planes_share_in_its_own_column_when_charged():
    autopower = str(Path(sys.executable).parent / "autopower")
    args = [autopower, "evaluate", "paper-fig7", "--media", "laptop-robot=gsm"]
    on = subprocess.run([*args, "--control-plane"], capture_output=True, text=True, timeout=120,
                        env={"COLUMNS": "200", "PATH": ""})
    off = subprocess.run(args, capture_output=True, text=True, timeout=120, env={"COLUMNS": "200", "PATH": ""})
    assert on.returncode == 0 and off.returncode == 0, on.stderr + off.stderr
    assert "of which control W" in on.stdout and "of which control W" not in off.stdout
    assert "lifetime 29121.6 s" in off.stdout  # Fig. 7's row 4, as the paper prints it

    def lifetime(out: str) -> float:
        return float(re.search(r"^lifetime ([0-9.]+) s", out, re.M)[1])

    assert lifetime(on.stdout) < lifetime(off.stdout)


def test_up_runs_the_lease_keep_alives_and_status_period_the_scenario_plans_with():
    from autopower.cli.team import control_plane_settings
    from autopower.launch.localhost import TeamSpec

    default = load_scenario("paper-fig7").control_plane
    assert control_plane_settings(default, None) == {"lease_ms": 500, "keep_alive": 2, "status_period_s": 0.5,
                                                     "heartbeat_s": 2.0}
    relaxed = ScenarioParser(with_section("max_detection_s = 3.0\nstatus_period_s = 1.0"), "", "f.toml").scenario()
    settings = control_plane_settings(relaxed.control_plane, None)
    # the longest lease within 3 s, and a heartbeat of half of it: two missed show a stuck peer in time
    assert settings == {"lease_ms": 2000, "keep_alive": 2, "status_period_s": 1.0, "heartbeat_s": 1.5}
    assert control_plane_settings(relaxed.control_plane, 700)["lease_ms"] == 700  # --lease-ms wins
    spec = TeamSpec(scenario="paper-fig7", **settings)
    assert (spec.lease_ms, spec.keep_alive, spec.status_period_s, spec.heartbeat_s) == (2000, 2, 1.0, 1.5)
    slow = ScenarioParser(with_section("max_detection_s = 10.0"), "", "f.toml").scenario().control_plane
    assert (slow.lease_s, slow.heartbeat_s) == (10.0, 5.0)
    for section, said in (("heartbeat_s = 0.2", "heartbeat_s 0.2 is shorter than status_period_s 0.5"),
                          ("max_detection_s = 3.0\nheartbeat_s = 2.0", "heartbeat_s 2 is longer than half of "
                                                                       "max_detection_s 3")):
        with pytest.raises(ScenarioError, match=said):
            ScenarioParser(with_section(section), "", "f.toml").scenario()
    with pytest.raises(ScenarioError, match="control_plane.lease_s: found 0.05"):
        ScenarioParser(with_section("lease_s = 0.05"), "", "f.toml").scenario()


@pytest.mark.parametrize("heartbeat_s, whole_every", [(0.5, 20), (2.0, 5), (2.5, 4), (3.0, 4), (5.0, 2), (10.0, 1),
                                                     (20.0, 1)])
def test_a_status_to_the_base_station_goes_whole_once_a_keyframe_period_and_as_its_change_between(heartbeat_s,
                                                                                                  whole_every):
    """As the runtime sends them (`protocol.statuses`): whole at the first heartbeat 10 s or more
    after the last whole one."""
    from autopower.model.control_plane import KEYFRAME_EVERY_S, ControlPlaneSpec
    from autopower.protocol.statuses import KEY_EVERY_S

    assert KEYFRAME_EVERY_S == KEY_EVERY_S
    spec = ControlPlaneSpec(enabled=True, heartbeat_s=heartbeat_s, status_bytes=1000, status_change_bytes=100)
    assert spec.status_mean_bytes() == pytest.approx((1000 + (whole_every - 1) * 100) / whole_every)
