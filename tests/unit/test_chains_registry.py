"""The component registry the runtime builds sources and components from, and the profiler."""

import pytest

from autopower.chains import (
    Component,
    ComponentType,
    Source,
    UnknownComponentTypeError,
    component_types,
    make_component,
    make_source,
    profile_components,
    register_component_type,
    score_output,
    unregister_component_type,
)
from autopower.errors import AutoPowerError


def test_builtin_types_are_the_scenario_names():
    assert component_types() == ("Blob", "Loc", "TeamMap")


@pytest.mark.parametrize("factory", [make_source, make_component])
def test_unknown_type_is_a_clear_key_error_listing_known_types(factory):
    with pytest.raises(UnknownComponentTypeError) as excinfo:
        factory("Planner", "r1", 0)
    error = excinfo.value
    assert isinstance(error, KeyError) and isinstance(error, AutoPowerError)
    assert str(error) == "unknown component type 'Planner'; known types: 'Blob', 'Loc', 'TeamMap'"


def test_instance_name_instead_of_type_gets_a_hint():
    with pytest.raises(KeyError, match="'Loc-2' looks like a component instance; its type is 'Loc'"):
        make_component("Loc-2", "r2", 0)


@pytest.mark.parametrize(("robot", "seed", "message"), [("", 0, "robot"), ("r1", -1, "seed"), ("r1", 1.5, "seed")])
def test_bad_robot_or_seed_is_rejected(robot, seed, message):
    with pytest.raises(ValueError, match=message):
        make_source("Loc", robot, seed)


@pytest.mark.parametrize("kind", ["Blob", "Loc"])
def test_sources_and_components_follow_the_protocols_and_score(kind):
    source = make_source(kind, "r2", 4)
    component = make_component(kind, "r2", 4)
    assert isinstance(source, Source) and isinstance(component, Component)
    assert source.component_type == component.component_type == kind
    assert source.robot == component.robot == "r2"
    output = component.run(source.produce(0))
    scores = score_output(kind, source.ground_truth(0), output)
    good = scores["victims_found"] == scores["victims_total"] if kind == "Blob" else scores["position_error_m"] < 0.3
    assert good, scores
    fresh = make_component(kind, "r2", 4)
    fresh.import_state(component.export_state())
    assert fresh.run(source.produce(1)) == component.run(source.produce(1))


def test_loc_component_belongs_to_its_robot_wherever_it_runs():
    loc_2 = make_component("Loc", "r2", 0)  # e.g. running on the laptop
    assert loc_2.run(make_source("Loc", "r2", 0).produce(0))
    with pytest.raises(ValueError, match="from robot 'r1' but this filter localises 'r2'"):
        loc_2.run(make_source("Loc", "r1", 0).produce(0))


class _EchoSource:
    component_type = "Echo"

    def __init__(self, robot, seed):
        self.robot, self.seed = robot, seed

    def produce(self, seq):
        return f"{self.robot}:{self.seed}:{seq}".encode()

    def ground_truth(self, seq):
        return {"text": f"{self.robot}:{self.seed}:{seq}"}


class _Echo:
    component_type = "Echo"

    def __init__(self, robot):
        self.robot = robot

    def run(self, payload):
        return payload

    def export_state(self):
        return b""

    def import_state(self, state):
        pass


def test_a_new_type_can_be_registered_and_is_then_profiled():
    spec = ComponentType(
        name="Echo", make_source=_EchoSource, make_component=lambda robot, seed: _Echo(robot),
        score=lambda truth, out: {"ok": float(out.decode() == truth["text"])},
    )
    register_component_type(spec)
    try:
        assert "Echo" in component_types()
        source = make_source("Echo", "r1", 3)
        output = make_component("Echo", "r1", 3).run(source.produce(2))
        assert score_output("Echo", source.ground_truth(2), output) == {"ok": 1.0}
        with pytest.raises(ValueError, match="already registered"):
            register_component_type(spec)
        assert profile_components(runs=2, types=["Echo"])["Echo"]["input_bytes"] == len(b"r1:0:0")
    finally:
        unregister_component_type("Echo")
    assert "Echo" not in component_types()


def test_profile_reports_latencies_and_the_message_sizes():
    profile = profile_components(runs=3)
    assert set(profile) == {"Blob", "Loc", "TeamMap"}
    blob, loc = profile["Blob"], profile["Loc"]
    assert blob["input_bytes"] == blob["input_bytes_max"] == 230415
    assert 0 < blob["output_bytes"] <= blob["output_bytes_max"] <= 200
    assert abs(loc["input_bytes"] - 1059) <= 11 and abs(loc["output_bytes"] - 805) <= 9
    for entry in profile.values():
        assert entry["runs"] == 3
        assert 0 < entry["latency_min_s"] <= entry["latency_median_s"] <= entry["latency_max_s"] < 1.0
        assert entry["latency_min_s"] <= entry["latency_mean_s"] <= entry["latency_max_s"]


@pytest.mark.parametrize("runs", [0, -1, 2.5, True])
def test_profile_runs_must_be_a_positive_int(runs):
    with pytest.raises(ValueError, match="runs"):
        profile_components(runs=runs)
