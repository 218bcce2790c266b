"""A real agent or base station with its bus tapped by a Recorder (run by test_recorder_zenoh.py).

``python -m tests.integration.recorder_node base|agent RUN_DIR PORT SECONDS`` — this is exactly the
integration recipe the runtime's process commands follow.
"""

from __future__ import annotations

import logging
import os
import sys

os.environ.setdefault("RERUN_ANALYTICS", "0")


def main(role: str, run_dir: str, port: int, seconds: float) -> None:
    from autopower.agent.process import Agent, AgentConfig
    from autopower.basestation.coordinator import CoordinatorConfig
    from autopower.basestation.process import BaseStation, BaseStationConfig
    from autopower.model.loading import load_scenario
    from autopower.node.runtime import NodeRuntime
    from autopower.recording.live import open_recorder
    from autopower.runtime.bus import ZenohBus, ZenohSettings

    logging.basicConfig(level=logging.WARNING)
    scenario = load_scenario("paper-fig7")
    endpoint = f"tcp/127.0.0.1:{port}"
    if role == "base":
        settings = ZenohSettings(listen=(endpoint,), lease_ms=500)
        recorder = open_recorder(run_dir, scenario.basestation, scenario=scenario)
        config = BaseStationConfig(scenario=scenario, team="rec", zenoh=settings, status_period_s=0.2,
                                   coordinator=CoordinatorConfig(speed=20.0, start_grace_s=1.0))
        with recorder.tap(ZenohBus(settings)) as bus, \
                BaseStation(config, host_factory=NodeRuntime, bus=bus) as process:
            recorder.attach(process.runtime)
            process.run(max_wall_s=seconds)
            recorder.record_stop(process.runtime)
    else:
        settings = ZenohSettings(connect=(endpoint,), lease_ms=500)
        recorder = open_recorder(run_dir, "r1", scenario=scenario)
        config = AgentConfig(robot="r1", scenario=scenario, team="rec", zenoh=settings, status_period_s=0.2)
        with recorder.tap(ZenohBus(settings)) as bus, Agent(config, bus=bus) as process:
            recorder.attach(process.runtime)
            process.run(max_wall_s=seconds)
            recorder.record_stop(process.runtime)
    print(f"{role} done, recorder errors {recorder.errors}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]))
