"""Battery metering from real (simulated) activity agrees with the energy model.

A whole team runs deterministically (manual clock, in-memory bus) and every robot's metered
energy over a window is compared with `evaluate(...)` of the same allocation and network.
"""

from __future__ import annotations

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.energy import airtime_s, evaluate
from autopower.model.loading import load_scenario
from autopower.node.meter import BatteryMeter, part
from tests.unit.sim_team import SimTeam

LAPTOP = {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "laptop", "Blob-3": "laptop"}
LOCAL = {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}
MIXED = {"Loc-1": "r2", "Loc-2": "laptop", "Loc-3": "r1", "Blob-2": "r3", "Blob-3": "r3"}  # r1 relays over GSM
GSM_ROW = {"Loc-1": "r1", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "r2", "Blob-3": "r3"}  # a Fig. 7 row


def test_meter_arithmetic():
    sc = load_scenario("paper-fig7")
    radio = sc.radios["802.11a"]
    m = BatteryMeter(platform=sc.platforms["sitsang"], radios=sc.radios, initial_j=100.0, t0=0.0,
                     media=["802.11a"])
    m.advance(10.0)
    assert m.energy_j["cpu_idle"] == pytest.approx(13.4)
    assert m.energy_j[part("802.11a", "sleep")] == pytest.approx(0.1)
    m.charge_run(0.85, 10.0)
    assert m.energy_j["cpu_busy"] == pytest.approx(0.93 * 0.85)
    air = airtime_s(230415, radio)
    m.charge_radio("send", "802.11a", 230415, 0.25, 10.0)
    assert m.energy_j[part("802.11a", "send")] == pytest.approx(radio.send_w * air * 0.25)
    assert m.energy_j[part("802.11a", "sleep")] == pytest.approx(0.1 - radio.sleep_w * air * 0.25)
    m.charge_radio("receive", "802.11a", 805, 2.0, 10.0)
    assert m.energy_j[part("802.11a", "receive")] == pytest.approx(radio.receive_w * airtime_s(805, radio) * 2)
    m.charge_radio("send", "802.11a", 1000, 1.0, 10.0, purpose="migration")
    assert m.energy_j[part("802.11a", "migration")] > 0
    assert m.battery_j == pytest.approx(100.0 - m.consumed_j)
    power, util = m.window(20.0, 100.0)
    assert util == pytest.approx(0.85 / 20.0)


def test_overheads_the_model_leaves_out_are_metered_apart():
    sc = load_scenario("paper-fig7")
    radio = sc.radios["802.11a"]
    m = BatteryMeter(platform=sc.platforms["sitsang"], radios=sc.radios, initial_j=100.0, t0=0.0,
                     media=["802.11a"])
    m.charge_run(0.85, 1.0)
    m.charge_run(0.85, 1.0, purpose="recovery")  # a restarted stage recomputing a lost input
    m.charge_radio("send", "802.11a", 1000, 1.0, 1.0, purpose="recovery")  # a resent frame
    m.charge_radio("send", "802.11a", 2000, 1.0, 1.0, purpose="migration")
    assert m.energy_j["cpu_busy"] == pytest.approx(m.energy_j["cpu_recovery"])
    over = m.overhead_j()
    assert over["recovery"] == pytest.approx(0.93 * 0.85 + radio.send_w * airtime_s(1000, radio))
    assert over["migration"] == pytest.approx(radio.send_w * airtime_s(2000, radio))
    assert m.battery_j == pytest.approx(100.0 - m.consumed_j)  # the battery pays for all of it


def test_mains_meter_pays_nothing():
    sc = load_scenario("paper-fig7")
    m = BatteryMeter(platform=sc.platforms["laptop"], radios=sc.radios, initial_j=None, t0=0.0, media=["gsm"])
    m.advance(100.0)
    m.charge_run(1.0, 100.0)
    m.charge_radio("send", "gsm", 10**6, 1.0, 100.0)
    assert m.consumed_j == 0.0 and m.battery_j is None and not m.depleted


def test_depletion():
    sc = load_scenario("paper-fig7")
    m = BatteryMeter(platform=sc.platforms["sitsang"], radios=sc.radios, initial_j=1.34, t0=0.0)
    m.advance(0.5)
    assert not m.depleted
    m.advance(1.01)
    assert m.depleted


@pytest.mark.parametrize("accounting", ["paper", "physical"])
@pytest.mark.parametrize("topology, media, allocation", [
    ("fully-connected", {"laptop-robot": "802.11a", "robot-robot": "802.11a"}, LAPTOP),
    ("fully-connected", {"laptop-robot": "802.11a", "robot-robot": "802.11a"}, LOCAL),
    ("fully-connected", {"laptop-robot": "gsm", "robot-robot": "bluetooth"}, GSM_ROW),
    ("relay", {"laptop-robot": "802.11a", "robot-robot": "802.11a"}, LAPTOP),  # r1 forwards everything
    ("relay", {"laptop-robot": "gsm", "robot-robot": "802.11a"}, MIXED),
])
def test_metered_power_matches_the_model(accounting, topology, media, allocation):
    sc = load_scenario("paper-fig7").with_accounting(accounting)
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, topology=topology, media=media, pins=allocation,
                                                auto_replan=False))
    team.join()
    assert team.coordinator.ready and team.coordinator.placing.placement == allocation
    network = team.coordinator.deciding.plan_network
    assert network.media_by_group() == media
    ev = evaluate(sc, network, allocation, accounting=accounting)
    assert ev.feasible, ev.violations
    t0, t1 = 10.0, 110.0
    team.run_exchanging_statuses(t0)  # with the acknowledgements that free each robot's custody
    start = {r: team.energy(r) for r in ("r1", "r2", "r3")}
    team.run_exchanging_statuses(t1)
    for robot in ("r1", "r2", "r3"):
        measured_w = (team.energy(robot) - start[robot]) / (t1 - t0)
        assert measured_w == pytest.approx(ev.robots[robot].total_w, rel=2e-3), robot
        assert not team.nodes[robot].errors, team.nodes[robot].errors
    if topology == "relay" and allocation == LAPTOP:
        assert team.nodes["r1"].counters["forwarded"] > 0  # r2's and r3's frames went through r1's agent


def test_meter_parts_match_the_model_breakdown():
    sc = load_scenario("paper-fig7")
    media = {"laptop-robot": "gsm", "robot-robot": "802.11a"}
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, topology="relay", media=media, pins=MIXED,
                                                auto_replan=False))
    team.join()
    ev = evaluate(sc, team.coordinator.deciding.plan_network, MIXED)
    assert ev.feasible
    team.run_exchanging_statuses(20.0)
    before = {r: (team.energy(r), dict(team.nodes[r].meter.energy_j))[1] for r in ("r1", "r2", "r3")}
    team.run_exchanging_statuses(120.0)
    for robot in ("r1", "r2", "r3"):
        team.energy(robot)
        after = team.nodes[robot].meter.energy_j
        w = {k: (after.get(k, 0.0) - before[robot].get(k, 0.0)) / 100.0 for k in after}
        rp = ev.robots[robot]
        assert w["cpu_idle"] + w.get("cpu_busy", 0.0) == pytest.approx(rp.cpu_w, rel=2e-3)
        for medium, radio in rp.radios.items():
            assert w.get(part(medium, "send"), 0.0) == pytest.approx(radio.send_w, rel=2e-3, abs=1e-9)
            assert w.get(part(medium, "receive"), 0.0) == pytest.approx(radio.receive_w, rel=2e-3, abs=1e-9)
            assert w[part(medium, "sleep")] == pytest.approx(radio.sleep_w, rel=2e-3, abs=1e-12)
