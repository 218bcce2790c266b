"""A process at rest wakes for its deadlines, not every status period (issue 17, item 5).

Its status is built once per rest period (or when an event comes), a peer's silence is found when
its limit passes (the loop wakes for it), and anything timed (a source) keeps the period's ticks.
"""

from __future__ import annotations

import threading
import time

import pytest

from autopower.agent.process import Agent, AgentConfig
from autopower.model.loading import load_scenario
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.cadence import StatusCadence, next_silence_s
from autopower.runtime.clock import ManualClock
from autopower.runtime.events import WorkDone
from tests.unit.sim_team import FakeComponent, FakeSource
from tests.unit.test_status_cadence import status


def test_a_resting_node_with_nothing_timed_builds_its_next_status_when_the_rest_period_ends():
    cadence = StatusCadence(0.5, 2.0)
    assert not cadence.resting and cadence.next_build(0.0, quiet=True) == 0.0  # nothing sent yet: the tick
    cadence.due(status(0.0), 0.0)
    assert not cadence.resting and cadence.next_build(0.5, quiet=True) == 0.5  # it just spoke: the tick
    cadence.due(status(0.5), 0.5)  # nothing new: it announces the rest period
    assert cadence.resting
    assert cadence.next_build(1.0, quiet=True) == 2.5  # no tick before the rest period is over
    assert cadence.next_build(1.0, quiet=False) == 1.0  # something timed runs: every tick, as before
    assert cadence.next_build(3.0, quiet=True) == 3.0  # (never before the tick it was given)
    assert cadence.due(status(1.0), 1.0) is None  # what a tick in between would have built: held back
    assert cadence.due(status(2.5, battery=99.0), 2.5).next_status_s == 2.0  # the heartbeat goes out then
    cadence.due(status(2.7, hosted={"Blob-1": "running"}), 2.7)  # something new: out, the normal cadence
    assert not cadence.resting and cadence.next_build(3.0, quiet=True) == 3.0


def test_the_first_silence_deadline_is_the_earliest_heard_plus_limit_of_the_watched_nodes():
    assert next_silence_s({}, {"r2": 1.0}) is None  # not heard yet: no deadline (its token is enough)
    heard = {"r2": 10.0, "r3": 11.0, "laptop": 5.0}  # laptop no longer watched (out of sight already)
    assert next_silence_s(heard, {"r2": 4.0, "r3": 1.0}) == 12.0
    assert next_silence_s(heard, {"r2": 1.0, "r3": 1.0}) == 11.0


@pytest.fixture
def agent():
    hub = InMemoryHub(synchronous=True)
    scenario = load_scenario("paper-fig7")
    clock = ManualClock(speed=1.0, epoch_unix=time.time())
    config = AgentConfig(robot="r1", scenario=scenario, team="t")
    process = Agent(config, bus=hub.bus("r1"), make_component=FakeComponent, make_source=FakeSource,
                    clock_factory=lambda mission: clock).__enter__()
    builds: list[float] = []
    real = process.runtime.status
    process.runtime.status = lambda *a, **kw: builds.append(time.time()) or real(*a, **kw)
    yield process, builds
    process.__exit__(None, None, None)


def run_for(process: Agent, seconds: float, events=()) -> float:
    """Run ``process``'s loop for ``seconds`` of wall time, posting each (delay, event) meanwhile."""
    t0 = time.time()
    timers = [threading.Timer(delay, process.events.post, (event,)) for delay, event in events]
    for timer in timers:
        timer.start()
    process.run(max_wall_s=seconds)
    for timer in timers:
        timer.join()
    return t0


def test_an_agent_at_rest_builds_its_status_once_per_rest_period_and_at_once_for_an_event(agent):
    process, builds = agent
    t0 = run_for(process, 3.3, events=[(1.4, WorkDone())])
    offsets = [round(t - t0, 1) for t in builds[:-1]]  # (the last: its status on the way out)
    # two statuses 0.5 s apart (the second finds it at rest), the event's at once, the rest period's
    # heartbeat 2 s after the last sent: every 0.5 s, as before, would have been 7 builds
    assert len(offsets) == 4, offsets
    assert offsets[:2] == [0.0, 0.5] and abs(offsets[2] - 1.4) <= 0.15 and abs(offsets[3] - 2.5) <= 0.15, offsets


def test_a_peer_that_falls_silent_is_found_when_its_limit_passes_while_the_agent_rests(agent):
    process, _ = agent
    process.watch.on_token("r2", True)  # r2's token is here, its last status came now, with the normal period
    heard = time.time()
    process.watch.on_status("r2", 0.0, heard)
    limit = process.watch.limits()["r2"]  # asked now: out of sight, it is not watched any more
    found = []
    real = process._sight
    process._sight = lambda node, visible: found.append((node, visible, time.time())) or real(node, visible)
    run_for(process, 2.0)
    assert [(n, v) for n, v, _ in found] == [("r2", False)] and "r2" in process.watch.silent
    # when its limit (two periods, never below the lease and a period) passed, not at a tick at rest
    # up to 2 s later
    assert 0.0 < found[0][2] - heard - limit <= 0.2, found[0][2] - heard


def test_an_agent_with_something_timed_keeps_the_status_period(agent, monkeypatch):
    process, builds = agent
    monkeypatch.setattr(process.runtime, "idle", lambda: False)  # e.g. frames in custody, a stage hosted
    t0 = run_for(process, 2.2)
    assert [round(t - t0, 1) for t in builds[:-1]] == [0.0, 0.5, 1.0, 1.5, 2.0]
