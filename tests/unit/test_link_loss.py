"""A lossy link costs its retransmissions: `[network] loss`, priced by `airtime_s` as 1 / (1 - loss).

The model, the scenario file, the evaluator, the planner and the live meter must all price a
message on a link that loses the share ``loss`` of its packets as 1 / (1 - loss) messages on both
of its ends, and nothing else; no loss (the default) must leave every figure exactly as before.
bench/bench_lossy_links.py measures the factor on the testbed; these tests time nothing.
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import ScenarioError
from autopower.model.energy import LoadSpace, airtime_s, evaluate, transmissions
from autopower.model.loading import load_scenario, parse_scenario
from autopower.model.network import build_network
from autopower.node.meter import BatteryMeter, part
from autopower.planner import PlanRequest, plan
from tests.unit.sim_team import SimTeam

PAPER = (resources.files("autopower.scenarios") / "paper-fig7.toml").read_text()
ANALYZE = 'analyze_topologies = ["fully-connected", "relay"]'
LAPTOP = {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "laptop", "Blob-3": "laptop"}
WIFI = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}
FIG7 = load_scenario("paper-fig7")


def lossy(loss: str, text: str = PAPER, where: str = "mission.toml"):
    """paper-fig7 with ``loss = {...}`` in its [network] table."""
    assert ANALYZE in text
    return parse_scenario(text.replace(ANALYZE, f"{ANALYZE}\nloss = {loss}"), where)


def error_of(loss: str, text: str = PAPER) -> str:
    with pytest.raises(ScenarioError) as info:
        lossy(loss, text)
    return str(info.value)


# ---- the model term --------------------------------------------------------------------------------


def test_no_loss_is_the_papers_airtime_bit_for_bit():
    radio = FIG7.radios["802.11a"]
    assert airtime_s(230415, radio, 0.0) == airtime_s(230415, radio) == 230415 * 8.0 / (54000 * 1024.0)


def test_loss_multiplies_airtime_by_the_expected_transmissions():
    radio = FIG7.radios["gsm"]
    assert transmissions(0.2) == pytest.approx(1.25, rel=1e-15)
    assert airtime_s(805, radio, 0.2) == pytest.approx(airtime_s(805, radio) / 0.8, rel=1e-15)
    assert airtime_s(805, radio, 0.5) == pytest.approx(2 * airtime_s(805, radio), rel=1e-15)


@pytest.mark.parametrize("bad", [1.0, 1.5, -0.1])
def test_a_loss_outside_0_1_is_refused(bad):
    with pytest.raises(ScenarioError, match=r"not a share of packets in \[0, 1\)"):
        airtime_s(100, FIG7.radios["802.11a"], bad)


def test_a_lossy_hop_costs_more_on_both_of_its_ends_and_only_there():
    """r2 -> r1 -> laptop in the relay topology, r1-r2 losing 20 %: that hop's send and receive
    airtime x 1.25, the r1 -> laptop hop as before."""
    sc = lossy('{ "r2-r1" = 0.2 }')
    assert sc.link_loss("r1", "r2") == sc.link_loss("r2", "r1") == 0.2 and sc.link_loss("r1", "laptop") == 0.0
    network = build_network(sc, "relay", WIFI)
    air = airtime_s(230415, sc.radios["802.11a"])
    loads = {}
    for scenario in (FIG7, sc):
        space = LoadSpace(scenario, network, "paper", scenario.energies_j())
        out = np.zeros(space.size)
        space.flow_load("r2", "laptop", 230415, 1.0, out)
        loads[scenario.name] = (space, out)
    space, out = loads[sc.name]
    _, clean = loads[FIG7.name]
    assert out[space.send_slot("r2", "802.11a")] == pytest.approx(air / 0.8, rel=1e-12)
    assert out[space.recv_slot("r1", "802.11a")] == pytest.approx(air / 0.8, rel=1e-12)
    assert out[space.send_slot("r1", "802.11a")] == clean[space.send_slot("r1", "802.11a")] == air
    assert out[space.recv_slot("laptop", "802.11a")] == clean[space.recv_slot("laptop", "802.11a")] == air


def test_the_evaluator_charges_a_lossy_links_messages_1_25_times_and_leaves_the_others():
    """Everything on the laptop, fully connected: all of r2's traffic crosses laptop-r2."""
    sc = lossy('{ "laptop-r2" = 0.2 }')
    network = build_network(sc, "fully-connected", WIFI)
    before, after = evaluate(FIG7, network, LAPTOP), evaluate(sc, network, LAPTOP)
    r2, r2_lossy = before.robots["r2"].radios["802.11a"], after.robots["r2"].radios["802.11a"]
    assert r2_lossy.send_w == pytest.approx(r2.send_w / 0.8, rel=1e-12)
    assert r2_lossy.receive_w == pytest.approx(r2.receive_w / 0.8, rel=1e-12)
    assert r2_lossy.busy == pytest.approx(r2.busy / 0.8, rel=1e-12)
    for robot in ("r1", "r3"):
        assert after.robots[robot] == before.robots[robot]
    assert after.lifetime_s < before.lifetime_s


def test_zero_loss_leaves_every_fig7_row_exactly_as_it_was():
    zero = lossy('{ "laptop-r1" = 0, "r2-r3" = 0.0 }')
    assert zero.network_spec.loss == {}
    for row in FIG7.reference_rows:
        network = build_network(FIG7, row.topology, row.media_by_group())
        assert evaluate(zero, network, row.allocation).to_dict() == evaluate(FIG7, network, row.allocation).to_dict()


# ---- the scenario file -----------------------------------------------------------------------------


def test_a_scenario_file_gives_each_link_its_loss(tmp_path):
    path = tmp_path / "lossy.toml"
    path.write_text(PAPER.replace(ANALYZE, f'{ANALYZE}\nloss = {{ "laptop-r1" = 0.1, "r3-r2" = 0.05 }}'))
    sc = load_scenario(path)
    assert sc.network_spec.loss == {frozenset(("laptop", "r1")): 0.1, frozenset(("r2", "r3")): 0.05}
    assert sc.link_loss("r1", "laptop") == 0.1 and sc.link_loss("r2", "r3") == 0.05
    assert sc.link_loss("r1", "r2") == 0.0 and FIG7.link_loss("r1", "laptop") == 0.0


@pytest.mark.parametrize("loss, found, expected", [
    ('{ "laptop-r1" = 1 }', 'network.loss."laptop-r1": found 1', "0 <= loss < 1"),
    ('{ "laptop-r1" = 1.2 }', 'network.loss."laptop-r1": found 1.2', "0 <= loss < 1"),
    ('{ "laptop-r1" = 10 }', 'network.loss."laptop-r1": found 10', "(0.1 for 10 %"),
    ('{ "laptop-r1" = -0.1 }', 'network.loss."laptop-r1": found -0.1', "0 <= loss < 1"),
    ('{ "laptop-r1" = "10%" }', "network.loss.\"laptop-r1\": found '10%'", "a number"),
    ('{ "laptop-r9" = 0.1 }', "network.loss.\"laptop-r9\": unknown node 'r9'", "r1, r2, r3, laptop"),
    ('{ "laptop" = 0.1 }', "network.loss.\"laptop\": 'laptop' does not name two nodes", '"A-B"'),
    ('{ "r1-r1" = 0.1 }', 'network.loss."r1-r1": a link from r1 to itself', "two different nodes"),
    ('{ "r1-laptop" = 0.1, "laptop-r1" = 0.2 }', 'network.loss."laptop-r1": the link laptop-r1 is listed twice',
     "one entry per link"),
    ('{ "r1-laptop" = 0, "laptop-r1" = 0.2 }', 'network.loss."laptop-r1": the link laptop-r1 is listed twice',
     "one entry per link"),
    ("0.1", "network.loss: found 0.1", 'loss = { "laptop-r1" = 0.1 }'),
])
def test_a_bad_loss_names_the_file_line_and_key_and_says_what_to_give(loss, found, expected):
    msg = error_of(loss)
    assert found in msg and expected in msg, msg
    line = int(msg.split("mission.toml:")[1].split(":")[0])
    assert lossy_text(loss).splitlines()[line - 1].startswith("loss = "), msg


def lossy_text(loss: str) -> str:
    return PAPER.replace(ANALYZE, f"{ANALYZE}\nloss = {loss}")


def test_a_loss_on_nodes_without_a_link_is_refused():
    relay_only = PAPER.replace('topology = "fully-connected"', 'topology = "relay"').replace(
        ANALYZE, 'analyze_topologies = ["relay"]')
    text = relay_only.replace('analyze_topologies = ["relay"]', 'analyze_topologies = ["relay"]\n'
                                                                 'loss = { "laptop-r2" = 0.1 }')
    with pytest.raises(ScenarioError, match='network.loss."laptop-r2": laptop and r2 have no link in the topologies '
                                            "planned"):
        parse_scenario(text, "mission.toml")
    assert parse_scenario(text.replace("laptop-r2", "laptop-r1"), "m.toml").link_loss("r1", "laptop") == 0.1


# ---- the planner -----------------------------------------------------------------------------------

OFFLOAD = """
[scenario]
name = "offload"
accounting = "physical"
lifetime_rounding_s = 0

[platforms.robot]
idle_w = 1.0
busy_w = 2.0

[platforms.base]
mains = true

[radios.wifi]
kbps = 8000
sleep_w = 0.01
send_w = 1.0
receive_w = 1.0

[basestation]
name = "laptop"
platform = "base"

[[robots]]
name = "r1"
platform = "robot"
energy_j = 10000

[network]
topology = "fully-connected"
laptop_robot_media = ["wifi"]
robot_robot_media = ["wifi"]
LOSS

[components.Detect]
latency_s = { robot = 0.3, base = 0.01 }

[[chains]]
name = "Detect-1"
source = "r1"
sink = "operator"
period_s = 1.0
component = "Detect"
message_bytes = [256000, 100]
"""


def offload(loss: float):
    """One robot, a detector fed 256,000 B a second: 0.25 s of its radio (0.2475 W above sleep) on
    the laptop, or 0.3 W of its CPU at home. The radio is cheaper, until the link loses 20 %
    (0.2475 / 0.8 = 0.309 W)."""
    return parse_scenario(OFFLOAD.replace("LOSS", f'loss = {{ "r1-laptop" = {loss} }}'), "offload.toml")


@pytest.mark.parametrize("method", ["auto", "exhaustive"])
def test_a_lossy_link_moves_the_stage_home(method):
    clean = plan(PlanRequest(scenario=offload(0.0), method=method))
    lossy_plan = plan(PlanRequest(scenario=offload(0.2), method=method))
    assert clean.allocation == {"Detect-1": "laptop"}
    assert lossy_plan.allocation == {"Detect-1": "r1"}
    # the plan's lifetime is the lossy link's: 1.0 idle + 0.3 CPU + a 100 B result and sleep, not the offload's
    assert clean.lifetime_s == pytest.approx(10000 / (1.0 + 0.25 + 0.01 * 0.75))
    air = 100 * 8 / (8000 * 1024) / 0.8
    assert lossy_plan.lifetime_s == pytest.approx(10000 / (1.0 + 0.3 + air + 0.01 * (1 - air)))


def test_the_milp_sees_a_lossy_link_too():
    assert plan(PlanRequest(scenario=offload(0.2), method="milp")).allocation == {"Detect-1": "r1"}
    assert plan(PlanRequest(scenario=offload(0.0), method="milp")).allocation != {"Detect-1": "r1"}
    for loss in (0.0, 0.1, 0.2, 0.4):
        milp = plan(PlanRequest(scenario=offload(loss), method="milp"))
        best = plan(PlanRequest(scenario=offload(loss), method="exhaustive"))
        assert milp.lifetime_s == pytest.approx(best.lifetime_s, rel=1e-7), loss


# ---- the live meter --------------------------------------------------------------------------------


def test_the_meter_charges_a_lossy_peer_1_25_times_on_send_and_receive():
    radios = FIG7.radios
    meter = BatteryMeter(platform=FIG7.platforms["sitsang"], radios=radios, initial_j=64000, t0=0.0,
                         media=["802.11a"], loss={"laptop": 0.2})
    air = airtime_s(230415, radios["802.11a"])
    assert meter.charge_radio("send", "802.11a", 230415, 1.0, 0.0, peer="laptop") == pytest.approx(
        1.498 * air / 0.8, rel=1e-12)
    assert meter.charge_radio("receive", "802.11a", 230415, 1.0, 0.0, peer="laptop") == pytest.approx(
        1.2 * air / 0.8, rel=1e-12)
    assert meter.charge_radio("send", "802.11a", 230415, 1.0, 0.0, peer="r2") == pytest.approx(1.498 * air, rel=1e-12)
    assert meter.airtime_s["802.11a"] == pytest.approx(air * (1 / 0.8 + 1 / 0.8 + 1), rel=1e-12)


def test_a_team_on_lossy_links_meters_what_the_model_says():
    """The relay topology, everything on the laptop: r2's and r3's frames cross lossy robot links
    to r1, which forwards them over a lossy link to the laptop. Metered power = evaluate()'s."""
    sc = lossy('{ "r1-r2" = 0.2, "laptop-r1" = 0.1 }')
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, topology="relay", media=WIFI, pins=LAPTOP,
                                                auto_replan=False))
    team.join()
    assert team.coordinator.placing.placement == LAPTOP
    network = team.coordinator.deciding.plan_network
    ev, clean = evaluate(sc, network, LAPTOP), evaluate(FIG7, network, LAPTOP)
    t0, t1 = 10.0, 110.0
    team.run_exchanging_statuses(t0)  # with the acknowledgements that free each robot's custody
    start = {r: team.energy(r) for r in ("r1", "r2", "r3")}
    team.run_exchanging_statuses(t1)
    for robot in ("r1", "r2", "r3"):
        measured_w = (team.energy(robot) - start[robot]) / (t1 - t0)
        assert measured_w == pytest.approx(ev.robots[robot].total_w, rel=2e-3), robot
        assert not team.nodes[robot].errors, team.nodes[robot].errors
    for robot in ("r1", "r2"):  # the lossy links' ends pay more than on clean links
        assert ev.robots[robot].total_w > clean.robots[robot].total_w * 1.005  # 5x the tolerance above
    assert ev.robots["r3"].total_w == clean.robots["r3"].total_w
    assert team.nodes["r1"].meter.energy_j[part("802.11a", "send")] > 0
