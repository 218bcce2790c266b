"""The paper's published figures, reproduced by the model (docs/concepts/energy-model.md)."""

import pytest

from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.planner import PlanRequest, plan

FIG7 = load_scenario("paper-fig7")
FIG8 = load_scenario("paper-fig8")
LOCAL = {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}
LAPTOP = {k: "laptop" for k in LOCAL}


def net(scenario, topology, lr, rr):
    return build_network(scenario, topology, {"laptop-robot": lr, "robot-robot": rr})


@pytest.mark.parametrize("index", range(16))
def test_fig7_row_reproduced_exactly(index):
    row = FIG7.reference_rows[index]
    ev = evaluate(FIG7, net(FIG7, row.topology, row.laptop_robot, row.robot_robot), row.allocation)
    assert ev.feasible
    assert ev.lifetime_rounded_s == row.paper_lifetime_s


def test_fig7_has_all_sixteen_rows():
    assert len(FIG7.reference_rows) == 16


def test_57_percent_claim():
    best = plan(PlanRequest(scenario=FIG7))
    assert best.evaluation.lifetime_rounded_s == 45715.2
    assert set(best.allocation.values()) == {"laptop"}
    assert best.network.media_by_group() == {"laptop-robot": "802.11a", "robot-robot": "802.11a"}
    gsm_local = evaluate(FIG7, net(FIG7, "fully-connected", "gsm", "802.11a"), LOCAL).lifetime_rounded_s
    assert round(45715.2 / gsm_local - 1, 2) == 0.57
    # against the 802.11a all-local "baseline" the gain is 55 % (model-notes)
    baseline = evaluate(FIG7, net(FIG7, "fully-connected", "802.11a", "802.11a"), LOCAL).lifetime_rounded_s
    assert round(45715.2 / baseline - 1, 2) == 0.55


def test_bluetooth_prevents_offloading_counterintuitively():
    """Bluetooth is the frugal radio, yet choosing it for the laptop link forbids offloading blobs."""
    ev = evaluate(FIG7, net(FIG7, "fully-connected", "bluetooth", "bluetooth"), LAPTOP)
    assert not ev.feasible
    assert any(v.resource == "radio:bluetooth" for v in ev.violations)


def test_relay_gsm_bluetooth_64_and_78_percent():
    best = 45715.2
    relay = net(FIG7, "relay", "gsm", "bluetooth")
    local = evaluate(FIG7, relay, LOCAL).lifetime_rounded_s
    opt = plan(PlanRequest(scenario=FIG7, network=relay))
    # The paper says 64 % and 78 %; the model gives 64.7 % (it truncates) and 77.5 %.
    assert local / best == pytest.approx(0.647, abs=0.001)
    assert opt.evaluation.lifetime_rounded_s / best == pytest.approx(0.775, abs=0.001)
    # "the most efficient allocation ... is to have the robots offload their localization"
    assert {opt.allocation[f"Loc-{i}"] for i in (1, 2, 3)} == {"laptop"}
    assert opt.allocation["Blob-2"] == "r2" and opt.allocation["Blob-3"] == "r3"


def test_fig8_fully_connected_gsm_bluetooth_shifts_localisation_off_r1():
    p = plan(PlanRequest(scenario=FIG8, topology="fully-connected"))
    assert p.network.media_by_group() == {"laptop-robot": "gsm", "robot-robot": "bluetooth"}
    assert p.allocation["Loc-1"] in ("r2", "r3")  # shifted away from the robot with least energy
    assert p.evaluation.bottleneck == "r1"
    assert p.evaluation.lifetime_rounded_s == 23860.8


def test_fig8_relay_configuration_from_the_text_is_optimal():
    """'Robot-3 runs both blob-finders, Robot-2 runs localization for itself and Robot-3,
    Robot-1's localization is off-loaded to the basestation': optimal (tied) under the model."""
    stated = {"Loc-1": "laptop", "Loc-2": "r2", "Loc-3": "r2", "Blob-2": "r3", "Blob-3": "r3"}
    relay = net(FIG8, "relay", "802.11a", "802.11a")
    ev = evaluate(FIG8, relay, stated)
    p = plan(PlanRequest(scenario=FIG8, topology="relay"))
    assert ev.feasible
    assert ev.lifetime_rounded_s == p.evaluation.lifetime_rounded_s == 23694.4
    assert p.network.media_by_group() == {"laptop-robot": "802.11a", "robot-robot": "802.11a"}


def test_vc_radio_fault_reallocation():
    """V.C: r3 must use GSM to the laptop and Bluetooth to the robots."""
    faulted = net(FIG7, "fully-connected", "802.11a", "802.11a").with_node_media(
        "r3", laptop_robot="gsm", robot_robot="bluetooth")
    old = evaluate(FIG7, faulted, LAPTOP)
    assert not old.feasible  # "the existing allocation scheme cannot continue"
    p = plan(PlanRequest(scenario=FIG7, network=faulted))
    paper_opt = {"Loc-1": "laptop", "Loc-2": "laptop", "Blob-2": "laptop", "Loc-3": "r1", "Blob-3": "r3"}
    assert evaluate(FIG7, faulted, paper_opt).lifetime_rounded_s == p.evaluation.lifetime_rounded_s == 35687.2
    assert p.allocation["Loc-3"] == "r1" and p.allocation["Blob-3"] == "r3"
    local = evaluate(FIG7, faulted, LOCAL).lifetime_rounded_s
    assert local / p.evaluation.lifetime_rounded_s == pytest.approx(0.82, abs=0.005)  # paper: "80 %"


def test_cameras_off_lets_bluetooth_carry_localisation():
    """V.C: with the blob finders off, Bluetooth can support offloading localisation."""
    relay_bt = net(FIG7, "relay", "802.11a", "bluetooth")
    p = plan(PlanRequest(scenario=FIG7, network=relay_bt, disabled_chains=frozenset({"Blob-2", "Blob-3"})))
    assert set(p.allocation) == {"Loc-1", "Loc-2", "Loc-3"}
    assert all(host == "laptop" for host in p.allocation.values())
