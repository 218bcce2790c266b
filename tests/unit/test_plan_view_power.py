"""A node's own model power, priced from the chains that load it, is the whole team's figure for it."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.simulation.synthetic import paper_fleet
from tests.unit.sim_team import SimTeam

ROBOTS = 8


@pytest.fixture(scope="module")
def fleet_team():
    _, scenario = paper_fleet(ROBOTS, topology="neighbours", neighbours=1)
    team = SimTeam(scenario, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(1.0)
    return scenario, team


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_nodes_own_power_is_what_the_whole_teams_prediction_gives_it(fleet_team, data):
    """Any placement, any set of nodes out of reach (a partition seen from the node), every robot:
    `predict_power(own_only=True)` (what `set_out_of_reach` and `stage_left` use, O(the node's
    chains)) equals the full prediction's figure for the node (O(team) chains, each O(team))."""
    scenario, team = fleet_team
    nodes = scenario.node_names()
    robot = data.draw(st.sampled_from([r.name for r in scenario.robots]), label="robot")
    view = team.nodes[robot].plan_view
    stages = sorted(s.name for c in scenario.chains for s in c.stages)
    placement = {s: data.draw(st.sampled_from(nodes), label=s) for s in stages}
    out = data.draw(st.frozensets(st.sampled_from([n for n in nodes if n != robot]), max_size=3), label="out")
    view.set_out_of_reach(out)
    whole = view.predict_power(placement)
    own = view.predict_power(placement, own_only=True)
    assert set(own) <= {robot}
    if robot in whole:
        assert own[robot] == pytest.approx(whole[robot], rel=1e-12, abs=1e-12)
    else:
        assert own == {}
    view.set_out_of_reach(frozenset())
