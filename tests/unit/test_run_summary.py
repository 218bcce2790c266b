"""`run_summary`'s power comparison (docs/tutorials/demo.md): the metered power since the team was
ready against the model's for the plan, the start-up left out of the comparison but not hidden."""

from __future__ import annotations

import pytest

from autopower.launch.summary import at_ready_complete, complete_at_ready, placed_power_w, run_summary


def _snap(t: float, battery: float, predicted: float = 2.0) -> dict:
    return {"robots": {"r1": {"present": True, "predicted_w": predicted,
                              "status": {"initial_j": 1000.0, "battery_j": battery, "t_virtual": t}}}}


def test_power_error_compares_the_placed_configuration_not_the_start_up():
    # 5 s of start-up at 0.4 W (no stage placed yet), then 95 s at 2.0 W, the model's figure
    at_ready = _snap(5.0, 1000.0 - 5 * 0.4)
    end = _snap(100.0, 1000.0 - 5 * 0.4 - 95 * 2.0)
    r1 = run_summary(end, team="t", speed=10, ready_after_s=1.0, wall_s=10.0, at_ready=at_ready)["robots"]["r1"]
    assert r1["placed_power_w"] == pytest.approx(2.0)
    assert r1["power_error"] == pytest.approx(0.0, abs=1e-12)
    assert r1["mean_power_w"] == pytest.approx(1.92)  # the whole run's mean keeps the start-up
    # a meter off by 3 % in the placed configuration is still seen
    off = _snap(100.0, 1000.0 - 5 * 0.4 - 95 * 2.06)
    assert run_summary(off, team="t", speed=10, ready_after_s=1.0, wall_s=10.0,
                       at_ready=at_ready)["robots"]["r1"]["power_error"] == pytest.approx(0.03)
    # without the snapshot at ready (the demo), the whole run's mean is compared
    assert run_summary(end, team="t", speed=10, ready_after_s=-1.0,
                       wall_s=10.0)["robots"]["r1"]["power_error"] == pytest.approx(1.92 / 2.0 - 1)


@pytest.mark.parametrize("at_ready", [None, {}, {"status": {}}, {"status": {"battery_j": 990.0, "t_virtual": 100.0}}])
def test_no_usable_status_at_ready_gives_no_placed_power(at_ready):
    assert placed_power_w({"battery_j": 900.0, "t_virtual": 100.0}, at_ready) is None


def test_a_robot_not_yet_heard_at_ready_is_compared_from_its_first_status_after():
    # a large fleet is ready (every stage placed) before the base station hears each robot again
    at_ready = {"robots": {"r1": {"present": True, "status": {"initial_j": 1000.0, "battery_j": None,
                                                              "t_virtual": None}}}}
    later, end = _snap(10.0, 1000.0 - 10 * 0.4), _snap(100.0, 1000.0 - 10 * 0.4 - 90 * 2.0)
    assert run_summary(end, team="t", speed=1, ready_after_s=1.0, wall_s=10.0,
                       at_ready=at_ready)["robots"]["r1"]["power_error"] is None  # nothing to start from
    assert not at_ready_complete(at_ready)  # `testbed up --json` asks for snapshots until it is
    complete_at_ready(at_ready, later)
    assert at_ready_complete(at_ready)
    complete_at_ready(at_ready, end)  # a usable one stays: the comparison starts at the first
    r1 = run_summary(end, team="t", speed=1, ready_after_s=1.0, wall_s=10.0, at_ready=at_ready)["robots"]["r1"]
    assert r1["placed_power_w"] == pytest.approx(2.0) and r1["power_error"] == pytest.approx(0.0, abs=1e-12)


def test_a_status_sent_before_the_robot_ran_the_ready_plan_does_not_start_its_comparison():
    """A robot of a large fleet reports every 0.5 s: the snapshot at ready may hold its status from
    before its stage ran (and before the ready plan's epoch). Compared from it, its start-up counted
    as the placed configuration: the last robots of a 30-robot fleet read 2 % below the model."""
    def snap(t, battery, epoch, hosted):
        return {"epoch": 7, "placement": {"Blob-1": "r1", "Loc-1": "laptop"},
                "robots": {"r1": {"present": True, "predicted_w": 2.0,
                                  "status": {"initial_j": 1000.0, "battery_j": battery, "t_virtual": t,
                                             "plan_epoch": epoch, "hosted": hosted}}}}

    # at 10 s the robot still ran the plan before (epoch 6, its Blob finder not yet started): 0.4 W
    at_ready = snap(10.0, 1000.0 - 10 * 0.4, 6, {})
    # its Blob finder started at 10.5 s: 0.5 s more at 0.4 W, then 2.0 W, the model's figure
    first_running = snap(11.0, 1000.0 - 10 * 0.4 - 0.5 * 0.4 - 0.5 * 2.0, 7, {"Blob-1": "running"})
    end = snap(40.0, first_running["robots"]["r1"]["status"]["battery_j"] - 29 * 2.0, 9, {"Blob-1": "running"})
    stale = run_summary(end, team="t", speed=1, ready_after_s=1.0, wall_s=10.0, at_ready=at_ready)
    # what the old rule read: half a second of start-up in 30 s of comparison
    assert stale["robots"]["r1"]["power_error"] == pytest.approx((0.5 * 0.4 + 29.5 * 2.0) / 30 / 2.0 - 1)
    assert not at_ready_complete(at_ready)
    starting = snap(10.4, 1000.0 - 10.4 * 0.4, 7, {"Blob-1": "starting"})  # the new plan, not yet running
    complete_at_ready(at_ready, starting)
    assert not at_ready_complete(at_ready)
    complete_at_ready(at_ready, first_running)
    assert at_ready_complete(at_ready)
    r1 = run_summary(end, team="t", speed=1, ready_after_s=1.0, wall_s=10.0, at_ready=at_ready)["robots"]["r1"]
    assert r1["placed_power_w"] == pytest.approx(2.0) and r1["power_error"] == pytest.approx(0.0, abs=1e-12)


def test_the_overheads_the_model_leaves_out_are_shown_beside_the_comparison_not_in_it():
    """As the replay's check: the control plane's bytes (and migrations, recovery) are charged to the
    battery, reported as `placed_overhead_w`, and left out of `power_error`."""
    def snap(t: float, battery: float, control_j: float) -> dict:
        status = {"initial_j": 1000.0, "battery_j": battery, "t_virtual": t,
                  "energy_j": {"cpu_idle": 1000.0 - battery - control_j, "802.11a:control": control_j}}
        return {"robots": {"r1": {"present": True, "predicted_w": 2.0, "status": status}}}

    at_ready = snap(10.0, 1000.0 - 10 * 2.0 - 0.5, 0.5)
    end = snap(110.0, 1000.0 - 110 * 2.0 - 0.5 - 100 * 0.05, 0.5 + 100 * 0.05)  # 50 mW of control
    r1 = run_summary(end, team="t", speed=10, ready_after_s=1.0, wall_s=10.0, at_ready=at_ready)["robots"]["r1"]
    assert r1["placed_overhead_w"] == pytest.approx(0.05)
    assert r1["placed_power_w"] == pytest.approx(2.0) and r1["power_error"] == pytest.approx(0.0, abs=1e-12)


def test_each_process_says_the_cpu_its_runtime_and_its_components_used():
    end = _snap(100.0, 800.0)
    end["robots"]["r1"]["status"].update(runtime_cpu_s=1.5, component_cpu_s=0.25)
    end["basestation"] = {"runtime_cpu_s": 3.0, "component_cpu_s": 7.0, "sinks": {}}
    out = run_summary(end, team="t", speed=10, ready_after_s=1.0, wall_s=10.0)
    assert out["robots"]["r1"]["cpu_s"] == {"runtime": 1.5, "components": 0.25}
    assert out["basestation"]["cpu_s"] == {"runtime": 3.0, "components": 7.0}
    # a robot never heard from used nothing it could say
    end["robots"]["r2"] = {"present": False}
    assert run_summary(end, team="t", speed=10, ready_after_s=1.0,
                       wall_s=10.0)["robots"]["r2"]["cpu_s"] == {"runtime": 0.0, "components": 0.0}
