"""Policies as pure functions: the paper's V.C reallocations, migration costs, hysteresis, subgroups."""

import itertools
import json

import pytest

from autopower.errors import AutoPowerError
from autopower.model.energy import airtime_s, evaluate
from autopower.model.loading import load_scenario
from autopower.model.mission_events import MissionEvent
from autopower.model.network import build_network
from autopower.planner import PlanRequest, plan
from autopower.planner.problem import make_problem
from autopower.planner.timesharing import time_sharing_bound
from autopower.policies import (
    POLICY_NAMES,
    MigrationCosts,
    TeamState,
    candidate_networks,
    derive_network,
    make_policy,
    plan_moves,
    subgroup_reallocation,
    subgroups,
)
from autopower.simulation.synthetic import random_scenario

FIG7 = load_scenario("paper-fig7")
LAPTOP = {s: "laptop" for s in FIG7.stage_names()}
PAPER_VC = {"Loc-1": "laptop", "Loc-2": "laptop", "Blob-2": "laptop", "Loc-3": "r1", "Blob-3": "r3"}
ALL_80211A = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}
FREE = MigrationCosts(downtime_s=0.0, cpu_s=0.0, state_bytes_default=0)
VC = MissionEvent(at_s=3600, kind="radio-fault", robot="r3", laptop_robot="gsm", robot_robot="bluetooth")


def start_state(scenario=FIG7, topology=None, **kw):
    return TeamState(scenario=scenario, time_s=0.0, network=build_network(scenario, topology), allocation={},
                     energies_j=scenario.energies_j(), topology=topology, **kw)


def vc_state(**kw):
    """Fig. 7's optimum running, one hour in, when r3's 802.11a card fails (Section V.C)."""
    faults = {"r3": ("gsm", "bluetooth")}
    network = derive_network(FIG7, None, ALL_80211A, radio_faults=faults)
    used = evaluate(FIG7, build_network(FIG7, None, ALL_80211A), LAPTOP)
    energies = {r: FIG7.robot(r).energy_j - used.robots[r].total_w * 3600 for r in ("r1", "r2", "r3")}
    return TeamState(scenario=FIG7, time_s=3600.0, network=network, allocation=dict(LAPTOP), energies_j=energies,
                     radio_faults=faults, events=(VC,), **kw)


@pytest.mark.parametrize("name", ["static", "reactive", "subgroup"])
def test_first_decision_is_the_planners_optimum(name):
    d = make_policy(name).decide(start_state())
    best = plan(PlanRequest(scenario=FIG7))
    assert d.allocation == best.allocation and d.network == best.network
    assert d.predicted_lifetime_s == pytest.approx(best.lifetime_s)
    assert d.forced and not d.moves and set(d.started) == set(FIG7.stage_names())


def test_rebalance_starts_a_time_sharing_schedule_worth_the_bound():
    state = start_state(topology="relay")
    d = make_policy("rebalance").decide(state)
    bound = time_sharing_bound(make_problem(PlanRequest(scenario=FIG7, topology="relay")), [])
    assert d.predicted_lifetime_s == pytest.approx(bound.lifetime_s, rel=1e-6)
    assert len(d.schedule) == 1 and d.revisit_at_s == pytest.approx(32737.9, abs=1.0)
    assert "time sharing over 2 configurations" in " ".join(d.reasons)


def test_rebalance_decides_a_fleet_too_large_to_enumerate_without_column_generation(monkeypatch):
    """A decision holds the coordinator up: a team whose configurations cannot be enumerated would
    price a MILP per column-generation round (66 s for 30 robots with cameras), so rebalance takes
    the best fixed configuration there, and its periodic replans follow the batteries."""
    from autopower.planner import timesharing
    from autopower.simulation.synthetic import paper_fleet

    _, fleet = paper_fleet(30)
    state = start_state(scenario=fleet)
    assert not timesharing.enumerable(make_problem(PlanRequest(scenario=fleet)))

    def refused(*args, **kwargs):
        raise AssertionError("column generation run inside a decision")

    monkeypatch.setattr(timesharing, "_by_column_generation", refused)
    d = make_policy("rebalance").decide(state)
    assert d.forced and not d.schedule and set(d.started) == set(fleet.stage_names())
    assert d.predicted_lifetime_s == pytest.approx(make_policy("static").decide(state).predicted_lifetime_s)
    # the paper's trio still gets its schedule (by enumeration)
    assert timesharing.enumerable(make_problem(PlanRequest(scenario=FIG7, topology="relay")))


@pytest.mark.parametrize("name", ["reactive", "rebalance", "subgroup"])
def test_vc_fault_gives_the_papers_reallocation(name):
    d = make_policy(name).decide(vc_state())
    assert d.forced
    assert dict(d.allocation) == PAPER_VC
    assert {m.stage for m in d.moves} == {"Loc-3", "Blob-3"}
    assert "r3 radio:gsm utilisation 1564.4% exceeds 100%" in d.reasons[0]
    assert d.network.medium_between("r1", "r2") == "802.11a"
    assert d.network.medium_between("r3", "laptop") == "gsm"


def test_static_reverts_to_local_computation_on_the_vc_fault():
    d = make_policy("static").decide(vc_state())
    assert d.forced
    assert all(host == "laptop" or host == stage_source for host, stage_source in [
        (d.allocation[s], FIG7.chain(s).source) for s in d.allocation])
    ev = evaluate(FIG7, d.network, d.allocation)
    assert ev.feasible
    best = make_policy("reactive").decide(vc_state())
    # the paper: local computation gives ~80 % of the reallocation (82 % under the model, from full batteries)
    assert d.predicted_lifetime_s / best.predicted_lifetime_s == pytest.approx(0.82, abs=0.02)


def test_cameras_off_gives_the_localisation_only_optimum():
    relay = build_network(FIG7, "relay", ALL_80211A)
    energies = {"r1": 50_000.0, "r2": 52_000.0, "r3": 52_000.0}
    off = MissionEvent(at_s=14400, kind="chain-disable", chains=("Blob-2", "Blob-3"))
    state = TeamState(scenario=FIG7, time_s=14400.0, network=relay, allocation=dict(LAPTOP), energies_j=energies,
                      topology="relay", disabled_chains=frozenset({"Blob-2", "Blob-3"}), events=(off,))
    d = make_policy("reactive").decide(state)
    assert set(d.stopped) == {"Blob-2", "Blob-3"}
    want = plan(PlanRequest(scenario=FIG7, topology="relay", energies_j=energies,
                            disabled_chains=frozenset({"Blob-2", "Blob-3"})))
    assert dict(d.allocation) == want.allocation == {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop"}
    # ... and, as V.C says, Bluetooth between the robots now carries that offloading too (within 0.2 %)
    bt = evaluate(FIG7, build_network(FIG7, "relay", {"laptop-robot": "802.11a", "robot-robot": "bluetooth"}), d.allocation,
                  energies_j=energies, disabled_chains=frozenset({"Blob-2", "Blob-3"}))
    assert bt.feasible and bt.lifetime_s > 0.998 * want.lifetime_s
    with_blobs = evaluate(FIG7, build_network(FIG7, "relay", {"laptop-robot": "802.11a", "robot-robot": "bluetooth"}),
                          LAPTOP)
    assert not with_blobs.feasible  # before, Bluetooth could not carry the images


def test_migration_cost_is_the_state_over_the_radios_crossed():
    costs = MigrationCosts(downtime_s=0.5, cpu_s=0.1, state_bytes={"Loc": 32_800, "Blob": 0})
    relay = build_network(FIG7, "relay", {"laptop-robot": "gsm", "robot-robot": "bluetooth"})
    # Loc-2 from the laptop to r2: laptop -> r1 over GSM, r1 -> r2 over Bluetooth
    [move] = plan_moves(FIG7, relay, {"Loc-2": "laptop"}, {"Loc-2": "r2"}, costs)
    gsm, bt = FIG7.radios["gsm"], FIG7.radios["bluetooth"]
    air_gsm, air_bt = airtime_s(32_800, gsm), airtime_s(32_800, bt)
    cpu = (2.27 - 1.34) * 0.1
    assert move.energy_j["r1"] == pytest.approx(gsm.receive_w * air_gsm + bt.send_w * air_bt)
    assert move.energy_j["r2"] == pytest.approx(bt.receive_w * air_bt + cpu)
    assert "laptop" not in move.energy_j  # mains powered
    assert move.transfer_s == pytest.approx(air_gsm + air_bt)
    assert move.missed_periods == 2  # (0.5 s + 2.4 s) / 2 s per run
    assert not move.state_lost
    # a stateless stage costs only CPU; an old host that is gone means a cold start
    [blob] = plan_moves(FIG7, relay, {"Blob-2": "laptop"}, {"Blob-2": "r2"}, costs)
    assert blob.energy_j == pytest.approx({"r2": cpu})
    gone = relay.without_nodes({"r3"})
    [cold] = plan_moves(FIG7, gone, {"Loc-1": "r3"}, {"Loc-1": "r1"}, costs)
    assert cold.state_lost and cold.energy_j == pytest.approx({"r1": cpu}) and cold.transfer_s == 0


def test_migration_costs_from_scenario_and_overrides():
    import dataclasses

    s = dataclasses.replace(FIG7, migration={"downtime_s": 2.0, "state_bytes_default": 100.0})
    c = MigrationCosts.from_scenario(s, {"cpu_s": 0.3, "state_bytes": {"Loc": 5}})
    assert (c.downtime_s, c.cpu_s, c.state_bytes_default) == (2.0, 0.3, 100)
    assert c.state_bytes_for("Loc") == 5 and c.state_bytes_for("Blob") == 100


def test_expensive_migrations_are_not_worth_it():
    """The same V.C choice, but moving state costs more than the gain: stay as long as possible."""
    state = start_state(topology="relay")
    cheap = make_policy("rebalance").decide(state)
    assert len(cheap.schedule) == 1
    # a 10 GB state over 802.11a costs ~2 kJ per move: the schedule no longer pays for itself
    costly = make_policy("rebalance").decide(start_state(topology="relay",
                                                        migration=MigrationCosts(state_bytes_default=10**10)))
    assert not costly.schedule and costly.predicted_lifetime_s == pytest.approx(41820.3, abs=0.1)


def test_rebalance_does_not_flap():
    """Asked again right after its decision, with nothing changed, rebalance moves nothing."""
    policy = make_policy("rebalance")
    first = policy.decide(start_state(topology="relay"))
    again = TeamState(scenario=FIG7, time_s=1.0, network=first.network, allocation=dict(first.allocation),
                      energies_j={r: e - 2.0 for r, e in FIG7.energies_j().items()}, topology="relay",
                      schedule=first.schedule)
    d = policy.decide(again)
    assert d is None or not d.moves


@pytest.mark.parametrize("name", POLICY_NAMES)
def test_nothing_happens_without_a_reason(name):
    """A policy asked with the optimum running and no event keeps it."""
    best = plan(PlanRequest(scenario=FIG7))
    state = TeamState(scenario=FIG7, time_s=10.0, network=best.network, allocation=best.allocation,
                      energies_j=FIG7.energies_j())
    d = make_policy(name).decide(state)
    assert d is None or not d.changes_anything


def test_candidate_networks_respect_faults_and_cuts():
    state = TeamState(scenario=FIG7, time_s=0.0, network=build_network(FIG7), allocation={}, energies_j={},
                      cut_links=frozenset({frozenset({"r1", "laptop"})}), radio_faults={"r3": ("gsm", None)})
    nets = candidate_networks(state)
    assert len(nets) == 4
    for n in nets:
        assert n.medium_between("r1", "laptop") is None
        assert n.medium_between("r3", "laptop") == "gsm"


def test_unknown_policy_is_a_clear_error():
    with pytest.raises(AutoPowerError, match="unknown policy 'greedy'; choose one of static, reactive"):
        make_policy("greedy")
    with pytest.raises(AutoPowerError, match="policy rebalance"):
        make_policy("rebalance", nonsense=1)


# ---- subgroups -------------------------------------------------------------------------------------


def test_subgroups_are_the_parts_that_reach_each_other():
    cut = build_network(FIG7)
    for r in ("r1", "r2", "r3"):
        cut = cut.without_link(r, "laptop")
    assert subgroups(cut) == [("r1", "r2", "r3")]
    assert subgroups(build_network(FIG7)) == [("r1", "r2", "r3", "laptop")]
    apart = cut.without_link("r1", "r2").without_link("r1", "r3")
    assert subgroups(apart) == [("r1",), ("r2", "r3")]


def test_subgroup_reallocation_is_the_exact_optimum_among_members():
    """With the whole team (base station included) and free migrations, it is the planner's optimum."""
    network = build_network(FIG7)
    energies = {"r1": 30_000.0, "r2": 60_000.0, "r3": 64_000.0}
    local = {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}
    p = subgroup_reallocation(FIG7, network, network.nodes, local, energies, migration=FREE)
    best = plan(PlanRequest(scenario=FIG7, network=network, energies_j=energies))
    assert p.min_lifetime_after_s == pytest.approx(best.lifetime_s)
    assert p.moves and p.search == "exhaustive"


def test_subgroup_without_the_base_station_keeps_stages_among_members_and_buffers_blobs():
    cut = build_network(FIG7)
    for r in ("r1", "r2", "r3"):
        cut = cut.without_link(r, "laptop")
    energies = {"r1": 20_000.0, "r2": 60_000.0, "r3": 60_000.0}
    p = subgroup_reallocation(FIG7, cut, ("r1", "r2", "r3"), LAPTOP, energies)
    assert set(p.allocation.values()) <= {"r1", "r2", "r3"}
    assert all(m.state_lost for m in p.moves)  # the laptop's copies are out of reach
    assert p.min_lifetime_before_s is None and p.min_lifetime_after_s > 0
    assert any("Blob-2: laptop is unreachable from r2; results are buffered at r2" in r for r in p.reasons)
    # every robot's CPU is full with its own localisation and blob finder: all local is the only way
    assert dict(p.allocation) == {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}


def _pairwise_local_search(scenario, network, allocation, energies, hosts):
    """Single moves and pairwise swaps until nothing improves: the local optimum issue 5 warns about."""
    def life(alloc):
        ev = evaluate(scenario, network, alloc, energies_j=energies)
        return ev.lifetime_s if ev.feasible else -1.0

    current, value = dict(allocation), life(allocation)
    while True:
        trials = [{**current, s: h} for s in current for h in hosts if h != current[s]]
        trials += [{**current, a: current[b], b: current[a]} for a, b in itertools.combinations(current, 2)
                   if current[a] != current[b]]
        best = max(trials, key=life)
        if life(best) <= value * (1 + 1e-9):
            return value
        current, value = best, life(best)


@pytest.mark.parametrize("seed", [28, 52])
def test_multi_party_moves_escape_the_pairwise_local_optimum(seed):
    s = random_scenario(seed, 3, 5, energy_spread=0.6)
    network, robots, energies = build_network(s), [r.name for r in s.robots], s.energies_j()
    local = {st.name: c.source for c in s.chains for st in c.stages}
    stuck = _pairwise_local_search(s, network, local, energies, robots)
    exact = subgroup_reallocation(s, network, robots, local, energies, migration=FREE, min_gain=0, min_gain_s=0)
    assert exact.min_lifetime_after_s > stuck * 1.005
    assert len({m.from_node for m in exact.moves} | {m.to_node for m in exact.moves}) == 3
    # the neighbourhood search used for large subgroups gets there too
    lns = subgroup_reallocation(s, network, robots, local, energies, migration=FREE, min_gain=0, min_gain_s=0,
                                max_enumeration=1)
    assert lns.search == "neighbourhood"
    assert lns.min_lifetime_after_s >= stuck * 1.005


def test_subgroup_rejects_a_member_not_on_the_network():
    with pytest.raises(AutoPowerError, match="subgroup member 'r9'"):
        subgroup_reallocation(FIG7, build_network(FIG7), ("r1", "r9"), LAPTOP, FIG7.energies_j())


def test_subgroup_proposes_nothing_without_gain():
    best = plan(PlanRequest(scenario=FIG7))
    network = best.network
    p = subgroup_reallocation(FIG7, network, network.nodes, best.allocation, FIG7.energies_j())
    assert not p.changes_anything and dict(p.allocation) == best.allocation
    assert "no reallocation gains more than" in p.reasons[0]


def test_a_base_station_view_with_a_stale_network_still_sees_the_cut():
    """The live coordinator may pass the plan's network plus the links it saw go down."""
    best = plan(PlanRequest(scenario=FIG7))
    cut = frozenset({frozenset({"r2", "laptop"}), frozenset({"r3", "laptop"}), frozenset({"r1", "laptop"})})
    state = TeamState(scenario=FIG7, time_s=100.0, network=best.network, allocation=best.allocation,
                      energies_j=FIG7.energies_j(), cut_links=cut)
    d = make_policy("reactive").decide(state)
    assert d.forced and "laptop" not in d.allocation.values()
    assert json.loads(json.dumps(d.to_dict()))["forced"] is True
