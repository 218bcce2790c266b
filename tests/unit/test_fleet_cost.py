"""The runtime's own work per event does not grow with what a node does not take part in (issue 33)."""

from __future__ import annotations

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from tests.unit.sim_team import SimTeam


def test_the_timer_looks_at_no_hosted_stage_for_fan_in_steps_without_a_flow_in_the_scenario():
    """`Frames.join_tick` runs at every timer; the base station's host of a 300-robot fleet hosts its
    stages by the hundred, and asking each whether a join step was due was an eighth of the simulator's
    time. Without a flow no stage joins inputs: it asks none."""
    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(5.0)
    laptop = team.nodes["laptop"]
    assert laptop.hosted and not laptop.flows.fan_in
    asked = []
    laptop.flows.ready = lambda *a, **k: asked.append(a) or iter(())
    laptop.frames.join_tick()
    assert asked == []
