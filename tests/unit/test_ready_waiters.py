"""Snapshot queries held until the team is ready (`SnapshotRequest.until_ready_s`, `ReadyWaiters`):
answered in the loop pass where the team gets ready, when their wait has passed, or when the base
station stops; never more than `MAX_HELD` of them held."""

from __future__ import annotations

import math
import threading
import time

import msgpack
import pytest

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.basestation.process import BaseStation, BaseStationConfig
from autopower.basestation.ready_waiters import MAX_HELD, ReadyWaiters
from autopower.errors import ProtocolError
from autopower.model.loading import load_scenario
from autopower.node.runtime import NodeRuntime
from autopower.protocol import Keys, OperatorReply, SnapshotRequest, decode, encode
from autopower.protocol.codec import MAGIC, PROTOCOL_VERSION
from autopower.protocol.messages import MAX_UNTIL_READY_S
from autopower.runtime.bus import InMemoryHub
from autopower.runtime.events import StopRequested
from tests.unit.sim_team import FakeComponent, FakeRequest, FakeSource


class TimedRequest(FakeRequest):
    """A query that notes when it was answered."""

    def __init__(self, key, payload):
        super().__init__(key, payload)
        self.answered_at: float | None = None

    def reply(self, payload):
        self.answered_at = time.monotonic()
        super().reply(payload)


def test_waiters_answer_everyone_once_ready_and_the_rest_when_their_wait_has_passed():
    waiters = ReadyWaiters()
    a, b, c = object(), object(), object()
    assert waiters.hold(a, 10.0) and waiters.hold(b, 20.0) and waiters.hold(c, 30.0)
    assert waiters.next_deadline() == 10.0
    assert waiters.due(False, 9.9) == []
    assert waiters.due(False, 20.0) == [a, b]  # each once, in the order they came
    assert waiters.due(False, 20.0) == [] and len(waiters) == 1 and waiters.next_deadline() == 30.0
    assert waiters.hold(a, 40.0)
    assert waiters.due(True, 0.0) == [c, a]  # ready: everyone, whatever their wait
    assert len(waiters) == 0 and waiters.next_deadline() is None


def test_waiters_hold_a_bounded_number_and_give_them_all_up_at_a_stop():
    waiters = ReadyWaiters()
    held = [object() for _ in range(MAX_HELD)]
    assert all(waiters.hold(r, 1e9) for r in held)
    assert not waiters.hold(object(), 1e9)  # full: the caller answers it at once
    assert waiters.take_all() == held and len(waiters) == 0


@pytest.mark.parametrize("wait", [-1.0, MAX_UNTIL_READY_S + 1, math.nan, math.inf])
def test_a_snapshot_request_with_a_wait_out_of_bounds_is_refused(wait):
    with pytest.raises(ValueError, match="until_ready_s"):
        SnapshotRequest(until_ready_s=wait)
    wire = msgpack.packb([MAGIC, PROTOCOL_VERSION, SnapshotRequest.KIND, [wait]])
    with pytest.raises(ProtocolError):  # from the network as well: garbled, not held
        decode(wire, SnapshotRequest)


def _base_station() -> BaseStation:
    """A base station with no robot: its team never gets ready. Its statuses every 3 s: nothing
    but a held query's wait wakes its loop in between."""
    config = BaseStationConfig(scenario=load_scenario("paper-fig7"), team="w", coordinator=CoordinatorConfig(speed=1.0),
                               status_period_s=3.0, status_rest_period_s=3.0)

    def host(**kw):
        return NodeRuntime(make_component=FakeComponent, make_source=FakeSource, **kw)

    return BaseStation(config, host_factory=host, bus=InMemoryHub().bus("laptop"))


@pytest.fixture
def base_station():
    with _base_station() as base:
        yield base


def _ask(base, until_ready_s: float) -> TimedRequest:
    request = TimedRequest(Keys("w").operator, encode(SnapshotRequest(until_ready_s=until_ready_s)))
    request.asked_at = time.monotonic()
    base.events.on_request(request)
    return request


def _run(base, seconds: float) -> threading.Thread:
    thread = threading.Thread(target=base.run, kwargs={"max_wall_s": seconds}, daemon=True)
    thread.start()
    return thread


def test_a_held_query_is_answered_when_its_wait_has_passed_and_one_without_a_wait_at_once(base_station):
    base = base_station
    held, plain = _ask(base, 0.4), _ask(base, 0.0)
    _run(base, 1.5).join(5.0)
    assert plain.replies and plain.answered_at - plain.asked_at < 0.3
    assert len(held.replies) == 1 and held.closed
    # not before its wait, and not much after: the loop wakes for it though nothing else happens
    assert 0.4 <= held.answered_at - held.asked_at < 0.9
    reply = decode(held.replies[0], OperatorReply)
    assert reply.ok and reply.snapshot["ready"] is False and "basestation" in reply.snapshot


def test_a_held_query_is_answered_in_the_pass_where_the_team_gets_ready(base_station, monkeypatch):
    base = base_station
    ready = threading.Event()
    monkeypatch.setattr(Coordinator, "ready", property(lambda self: ready.is_set()))
    held = _ask(base, 5.0)
    thread = _run(base, 3.0)
    time.sleep(0.5)
    assert not held.replies  # not ready: still held
    ready.set()
    became_ready = time.monotonic()
    _ask(base, 0.0)  # any event: the pass that handles it sees the team ready
    thread.join(5.0)
    assert len(held.replies) == 1 and held.answered_at - became_ready < 0.3


def test_a_stopping_base_station_answers_what_it_holds_and_a_full_list_is_not_held():
    with _base_station() as base:
        held = [_ask(base, 20.0) for _ in range(MAX_HELD + 1)]
        base.events.post(StopRequested("test"), bulk=True)  # after every query
        base.run(max_wall_s=5.0)
        assert base.stop_reason == "test"
        assert [bool(r.replies) for r in held] == [False] * MAX_HELD + [True]  # the one beyond, at once
    # leaving the base station: the held ones get the snapshot as it is
    assert all(len(r.replies) == 1 and r.closed for r in held)
    assert all(decode(r.replies[0], OperatorReply).ok for r in held)
