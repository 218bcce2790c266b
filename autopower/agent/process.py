"""The robot agent process: one event loop around a `NodeRuntime`, a battery, a liveliness token.

`autopower agent --robot r2 --scenario paper-fig7 ...` builds an `Agent` and runs it. It
joins Zenoh, declares ``alive/<robot>``, waits for the base station's plan (which carries the
mission clock and starting energies), then hosts what it is assigned, runs its chains' sources
at their periods, forwards other robots' data when it sits on their route, meters its battery
and publishes its status at a steady wall-clock rate. When its battery is empty it publishes a
last status and leaves the team (the base station replans without it).
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field

from autopower.events import EventQueue, LivelinessChanged, OperatorRequest, Received, StopRequested
from autopower.agent.node import NodeRuntime
from autopower.bus import Bus, ZenohBus, ZenohSettings
from autopower.protocol import Keys, encode
from autopower.scenario import Scenario

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class AgentConfig:
    robot: str
    scenario: Scenario
    team: str
    zenoh: ZenohSettings = field(default_factory=ZenohSettings)
    status_period_s: float = 0.5  # wall seconds between status messages
    status_window_s: float = 2.0  # wall seconds the reported mean power covers
    parent_pid: int | None = None  # stop when this process is gone (no orphans)


class Agent:
    """A robot's agent (a context manager: the session, token and subscriptions close on exit)."""

    def __init__(self, config: AgentConfig, bus: Bus | None = None, **runtime_kwargs):
        config.scenario.robot(config.robot)  # unknown robot -> ScenarioError
        self.config = config
        self.keys = Keys(config.team)
        self.events = EventQueue(bulk_keys=[self.keys.node_data(config.robot)])
        self._bus = bus
        self._owns_bus = bus is None
        self._handles: list = []
        self._runtime_kwargs = runtime_kwargs
        self.runtime: NodeRuntime | None = None
        self.stop_reason: str | None = None

    def __enter__(self) -> "Agent":
        if self._bus is None:
            self._bus = ZenohBus(self.config.zenoh)
        bus, keys, robot = self._bus, self.keys, self.config.robot
        self.runtime = NodeRuntime(node=robot, scenario=self.config.scenario, bus=bus, keys=keys,
                                   **self._runtime_kwargs)
        for key in (keys.node_data(robot), keys.node_control(robot), keys.plan):
            self._handles.append(bus.subscribe(key, self.events.on_message))
        self._handles.append(bus.watch_liveliness(keys.alive_all, self.events.on_liveliness))
        # Presence last: once the base station sees us, everything we need is declared.
        self._handles.append(bus.declare_token(keys.alive(robot)))
        log.info("agent %s joined team %s", robot, self.config.team)
        return self

    def __exit__(self, *exc) -> None:
        for handle in reversed(self._handles):
            handle.close()
        self._handles.clear()
        if self._owns_bus and self._bus is not None:
            self._bus.close()
            self._bus = None

    def request_stop(self, reason: str) -> None:
        """Thread- and signal-safe."""
        self.events.post(StopRequested(reason))

    def _handle(self, event) -> None:
        rt = self.runtime
        if isinstance(event, Received):
            if not rt.on_message(event.key, event.payload):
                rt.count("unexpected-key", event.key)
        elif isinstance(event, LivelinessChanged):
            node = self.keys.node_of_alive(event.key)
            if node is not None:
                rt.on_liveliness(node, event.alive)
        elif isinstance(event, OperatorRequest):
            event.request.close()

    def publish_status(self) -> None:
        rt = self.runtime
        if not rt.started:
            return
        window = self.config.status_window_s * rt.clock.speed
        status = rt.status(window, self.events.depth())
        self._bus.publish(self.keys.status(self.config.robot), encode(status), reliable=False)

    def run(self, max_wall_s: float | None = None) -> str:
        """Run until stopped, depleted or ``max_wall_s``; return why it stopped."""
        rt = self.runtime
        deadline = None if max_wall_s is None else time.time() + max_wall_s
        next_status = time.time()
        while True:
            now = time.time()
            wake = [next_status]
            if deadline is not None:
                wake.append(deadline)
            if rt.started and (t := rt.next_deadline()) is not None:
                wake.append(rt.clock.wall_at(t))
            event = self.events.get(max(0.0, min(wake) - now))
            if isinstance(event, StopRequested):
                self.stop_reason = event.reason
                break
            if event is not None:
                try:
                    self._handle(event)
                except Exception:  # a bug in one handler must not kill the robot's software
                    log.exception("agent %s: error handling %r", self.config.robot, type(event).__name__)
                    rt.count("internal-error")
            if rt.started:
                rt.on_timer()
                rt.meter.advance(rt.now())
                if rt.meter.depleted:
                    log.warning("agent %s: battery empty at t=%.1f s; leaving the team", self.config.robot,
                                rt.now())
                    self.stop_reason = "depleted"
                    break
            now = time.time()
            if now >= next_status:
                self.publish_status()
                next_status = max(next_status + self.config.status_period_s, now)
                if self.config.parent_pid is not None and os.getppid() != self.config.parent_pid:
                    self.stop_reason = "parent exited"
                    break
            if deadline is not None and now >= deadline:
                self.stop_reason = "time limit"
                break
        self.publish_status()
        log.info("agent %s stopping: %s", self.config.robot, self.stop_reason)
        return self.stop_reason
