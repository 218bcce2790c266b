"""The runtime's own CPU: what a node's process spends beyond its component code, measured on the
computer running it and charged to a robot's battery through its platform's ``slowdown`` as
``cpu_runtime`` (autopower.node.guard, BatteryMeter.charge_runtime, Metering.charge_runtime)."""

from __future__ import annotations

import dataclasses
import time

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import ScenarioError
from autopower.model.dvfs import FrequencyLevel
from autopower.model.loading import load_scenario, parse_scenario, resolve_scenario_path
from autopower.model.parts import CPU_RUNTIME, overhead_kind
from autopower.node.guard import GuardedCalls
from autopower.node.meter import BatteryMeter
from tests.unit.sim_team import SimTeam

SC = load_scenario("paper-fig7")
SITSANG = SC.platforms["sitsang"]


def _spin(cpu_s: float) -> float:
    """Burn ``cpu_s`` of this thread's CPU; returns what it burnt."""
    start = time.thread_time()
    while time.thread_time() - start < cpu_s:
        sum(range(1000))
    return time.thread_time() - start


class Foreign:  # a component that does not ship with AutoPower: its calls go to the guard's worker thread
    def run(self, cpu_s: float) -> float:
        return _spin(cpu_s)

    def fail(self, cpu_s: float) -> float:
        _spin(cpu_s)
        raise ValueError("garbage in")


def test_the_paper_scenarios_say_how_much_slower_a_robot_runs_code():
    assert SITSANG.slowdown == 50.0  # the geometric mean of Fig. 5's blob finder (x11) and localiser (x243)
    assert SC.platforms["laptop"].slowdown is None  # mains powered: measured, never charged


def test_a_bad_slowdown_is_refused_where_it_is_written():
    text = resolve_scenario_path("paper-fig7")[1]
    for bad in ("0", "-3", '"fast"'):
        with pytest.raises(ScenarioError, match=r"platforms\.sitsang\.slowdown"):
            parse_scenario(text.replace("slowdown = 50 ", f"slowdown = {bad} "))
    assert parse_scenario(text.replace("slowdown = 50 ", "slowdown = 2.5 ")).platforms["sitsang"].slowdown == 2.5


def test_the_guard_counts_the_cpu_its_component_calls_take_on_either_thread():
    guard = GuardedCalls("t")
    try:
        burnt = guard.call(Foreign().run, 0.05, timeout_s=5.0)  # the worker thread
        assert guard.component_cpu_s == pytest.approx(burnt, abs=0.005)
        with pytest.raises(ValueError):  # a call that raises took CPU too
            guard.call(Foreign().fail, 0.03, timeout_s=5.0)
        assert guard.component_cpu_s >= burnt + 0.03
        before = guard.component_cpu_s
        burnt = guard.counted(_spin, 0.04)  # a constructor, on this thread
        assert guard.component_cpu_s - before == pytest.approx(burnt, abs=0.005)
        # the caller's own CPU while it waits is not the component's
        assert guard.component_cpu_s < time.process_time()
    finally:
        guard.close()


def test_a_robot_pays_its_runtimes_cpu_times_its_slowdown_apart_from_the_model():
    meter = BatteryMeter(platform=SITSANG, radios=SC.radios, initial_j=64_000.0, t0=0.0)
    joules = meter.charge_runtime(0.01, 1.0)  # 10 ms here: 0.5 s busy on the Sitsang
    assert joules == pytest.approx((SITSANG.busy_w - SITSANG.idle_w) * 0.01 * 50)
    assert meter.energy_j[CPU_RUNTIME] == pytest.approx(joules)
    assert overhead_kind(CPU_RUNTIME) == "runtime" and meter.overhead_j()["runtime"] == pytest.approx(joules)
    assert meter.runtime_cpu_s == pytest.approx(0.5)
    assert meter.cpu_busy_s == 0.0  # the model's utilisation (component runs) is not touched
    # at a slower DVFS level the same code takes longer, at that level's power
    slow = FrequencyLevel(name="100MHz", idle_w=0.5, busy_w=0.9, latency_factor=4.0)
    meter.set_level(slow, 2.0)
    assert meter.charge_runtime(0.01, 2.0) == pytest.approx(0.4 * 0.01 * 50 * 4.0)
    # carried across a restart with the rest of the meter
    saved = {"energy_j": meter.energy_j, "runtime_cpu_s": meter.runtime_cpu_s, "t_virtual": 2.0, "initial_j": 64_000.0}
    again = BatteryMeter(platform=SITSANG, radios=SC.radios, initial_j=64_000.0, t0=0.0)
    again.restore(saved)
    assert again.runtime_cpu_s == pytest.approx(0.5 + 2.0)


def test_no_slowdown_or_mains_power_pays_nothing():
    unknown = BatteryMeter(platform=dataclasses.replace(SITSANG, slowdown=None), radios=SC.radios,
                           initial_j=64_000.0, t0=0.0)
    mains = BatteryMeter(platform=SC.platforms["laptop"], radios=SC.radios, initial_j=None, t0=0.0)
    for meter in (unknown, mains):
        assert meter.charge_runtime(1.0, 1.0) == 0.0
        assert CPU_RUNTIME not in meter.energy_j


def test_a_node_charges_its_process_cpu_beyond_its_component_code_from_the_missions_start():
    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    r1 = team.nodes["r1"]
    r1.metering.charge_runtime(100.0)  # joining: no meter yet, the reading only sets where counting starts
    components_before = r1.guard.component_cpu_s
    team.join()
    team.run_until(2.0)  # builds its sources and runs its stages: component code
    r1.metering.charge_runtime(101.0)  # 1 s of process CPU since the mission started here...
    components = r1.guard.component_cpu_s - components_before
    assert 0 < components < 1.0
    assert r1.metering.component_cpu_s == pytest.approx(components)
    assert r1.metering.runtime_cpu_s == pytest.approx(1.0 - components)  # ...of which the components' is not the runtime's
    assert r1.meter.energy_j[CPU_RUNTIME] == pytest.approx((SITSANG.busy_w - SITSANG.idle_w) * (1.0 - components) * 50)
    r1.guard.component_cpu_s += 0.3  # a long run counted after the process reading: never negative
    r1.metering.charge_runtime(101.1)
    assert r1.metering.runtime_cpu_s == pytest.approx(1.0 - components)
    status = r1.status(1.0)
    assert status.runtime_cpu_s == pytest.approx(r1.metering.runtime_cpu_s)
    assert status.component_cpu_s == pytest.approx(components + 0.3)
    assert status.energy_j[CPU_RUNTIME] == pytest.approx(r1.meter.energy_j[CPU_RUNTIME])
