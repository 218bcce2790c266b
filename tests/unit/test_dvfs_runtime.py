"""DVFS at run time: the meter charges the plan's level, the base station's plans carry each
robot's level, and the simulator draws the power of the levels."""

import dataclasses

import pytest

from autopower.model.dvfs import apply_levels, level_named
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.node.meter import CPU_BUSY, CPU_IDLE, BatteryMeter
from autopower.planner import PlanRequest, plan
from autopower.simulation.simulator import simulate

DVFS = load_scenario("paper-pxa255-dvfs")


def test_meter_charges_the_level_it_is_set_to():
    sitsang = DVFS.platforms["sitsang"]
    meter = BatteryMeter(platform=sitsang, radios=DVFS.radios, initial_j=64000, t0=0.0)
    meter.advance(10.0)  # nominal (400 MHz) for 10 s
    assert meter.energy_j[CPU_IDLE] == pytest.approx(13.4)
    meter.set_level(level_named(DVFS, "r1", "200MHz"), 10.0)
    meter.charge_run(0.85, 12.0)  # one localisation: 0.85 s at 400 MHz takes 1.7 s at 200 MHz
    assert meter.energy_j[CPU_BUSY] == pytest.approx((1.5448 - 1.2696) * 0.85 * 2.0)
    assert meter.cpu_busy_s == pytest.approx(1.7)
    meter.set_level(None, 20.0)  # back to nominal: 10..20 s were idle at 200 MHz
    assert meter.energy_j[CPU_IDLE] == pytest.approx(13.4 + 1.2696 * 10)
    meter.advance(21.0)
    assert meter.energy_j[CPU_IDLE] == pytest.approx(13.4 + 1.2696 * 10 + 1.34)


def test_metering_a_level_reproduces_the_model():
    """One robot's steady state, charged run by run at its level, equals evaluate() at that level."""
    p = plan(PlanRequest(scenario=DVFS, method="exhaustive"))
    local = {c.name: c.source for c in DVFS.chains}
    network = build_network(DVFS, "fully-connected", {"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    levels = {"r1": "200MHz", "r2": "400MHz", "r3": "400MHz"}
    ev = evaluate(apply_levels(DVFS, levels), network, local)
    assert ev.feasible and ev.utilisation["r1"] == pytest.approx(0.85)
    meter = BatteryMeter(platform=DVFS.platforms["sitsang"], radios=DVFS.radios, initial_j=64000, t0=0.0)
    meter.set_level(level_named(DVFS, "r1", "200MHz"), 0.0)
    for k in range(50):  # Loc-1 runs locally every 2 s for 100 s
        meter.charge_run(DVFS.components["Loc"].latency_s["sitsang"], 2.0 * k)
    meter.advance(100.0)
    assert meter.consumed_j / 100.0 == pytest.approx(ev.robots["r1"].cpu_w, rel=1e-9)
    assert p.levels  # the planner's own choice carries levels too


def test_simulator_draws_the_levels_power():
    nominal = simulate(load_scenario("paper-fig7"), policy="static")
    scaled = simulate(DVFS, policy="static")
    best = plan(PlanRequest(scenario=DVFS, method="exhaustive"))
    assert scaled.lifetime_s > nominal.lifetime_s
    assert scaled.lifetime_s == pytest.approx(best.evaluation.lifetime_s, rel=1e-6)


def test_a_plan_naming_levels_round_trips_the_codec():
    import sys
    sys.path.insert(0, __file__.rsplit("/", 1)[0])
    from test_protocol import MISSION

    from autopower.errors import ProtocolError
    from autopower.protocol import LinkInfo, PlanUpdate, decode, encode

    update = PlanUpdate(epoch=3, mission=MISSION, placement={"Loc-1": "laptop"}, running={"Loc-1": 0},
                        links=(LinkInfo(a="r1", b="laptop", medium="802.11a"),), predicted_w={"r1": 1.26},
                        predicted_lifetime_s=None, plan_t_virtual=0.0, levels={"r1": "100MHz"},
                        variants={"Blob-2": "2fps"})
    back = decode(encode(update), PlanUpdate)
    assert back.levels == {"r1": "100MHz"} and back.variants == {"Blob-2": "2fps"}
    with pytest.raises(ProtocolError):  # a hostile plan: levels must map names to names
        decode(encode(dataclasses.replace(update, levels={"r1": 5})), PlanUpdate)


def test_levels_follow_the_placement_at_run_time():
    """Whatever moves a stage (here the operator), the next plan carries the levels that fit the new
    placement and the agent's meter switches to them."""
    from autopower.basestation.coordinator import CoordinatorConfig
    from autopower.protocol import MigrateCommand
    from tests.unit.sim_team import SimTeam

    team = SimTeam(DVFS, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    coord, r1 = team.coordinator, team.nodes["r1"]
    team.run_until(5.0)
    assert coord.placing.placement["Loc-1"] == "laptop" and r1.meter.level == "100MHz"
    reply = coord.on_operator(MigrateCommand(stage="Loc-1", to_node="r1"))
    assert reply.ok, reply.message
    team.run_until(10.0)
    assert coord.placing.placement["Loc-1"] == "r1"
    # Loc-1 is 42.5 % of r1 at 400 MHz: 200 MHz (85 %) fits, 100 MHz (170 %) does not
    assert coord.prediction.levels["r1"] == "200MHz" and r1.meter.level == "200MHz" and r1.meter.latency_factor == 2.0
    assert coord.deciding.plan_network is not None and team.nodes["r2"].meter.level == "100MHz"
    t0 = 20.0
    team.run_until(t0)
    e0 = team.energy("r1")
    team.run_until(t0 + 60.0)
    ev = evaluate(apply_levels(DVFS, coord.prediction.levels), coord.deciding.plan_network, coord.placing.placement)
    assert (team.energy("r1") - e0) / 60.0 == pytest.approx(ev.robots["r1"].total_w, rel=2e-3)


def test_simulator_runs_the_planned_variants_at_their_levels():
    s = load_scenario("paper-variants-dvfs").with_accounting("physical")
    best = plan(PlanRequest(scenario=s, method="exhaustive"))
    assert best.variants["Blob-2"] == "1fps"
    result = simulate(s, policy="static")
    # the static policy keeps the planned configuration: the simulated mission lives as planned
    assert result.lifetime_s == pytest.approx(best.evaluation.lifetime_s, rel=1e-6)
    assert result.lifetime_s > simulate(load_scenario("paper-pxa255-dvfs").with_accounting("physical"),
                                        policy="static").lifetime_s * 1.1
