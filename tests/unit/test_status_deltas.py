"""Statuses as their change from a whole one: a receiver's view is what the sender built, or it waits.

`protocol.statuses`: the sender's `StatusEncoder` sends a keyframe (the whole `NodeStatus`) and then
each status as its change from it; the receiver's `StatusAssembler` makes them whole again, ignores
a change whose keyframe it does not hold, and refuses a garbled one.
"""

from __future__ import annotations

import dataclasses

import msgpack
import pytest
from hypothesis import given, settings, strategies as st

from autopower.errors import ProtocolError
from autopower.protocol import MissionInfo, NodeStatus, SinkStats, SourceStats, StatusDelta, decode, encode
from autopower.protocol.codec import PROTOCOL_VERSION
from autopower.protocol.statuses import KEY_EVERY_S, StatusAssembler, StatusEncoder, replaces_queued
from autopower.runtime.events import EventQueue

PARTS = ("cpu_idle", "cpu_busy", "802.11a:send", "802.11a:receive", "802.11a:sleep", "gsm:send")


def status(t: float, node: str = "r1", **changes) -> NodeStatus:
    """A running robot's status at wall time 1000 + t: its clock, battery and meters move."""
    sink = SinkStats(run=0, received=int(t * 4), duplicates=0, contiguous=int(t * 4), max_seq=int(t * 4) - 1,
                     stale=0, latency_ms_p50=3.5, latency_ms_max=9.25, received_total=int(t * 4),
                     duplicates_total=0, digest=int(t * 7919))
    base = NodeStatus(node=node, t_virtual=t, t_unix=1000.0 + t, plan_epoch=3, initial_j=64000.0,
                      battery_j=64000.0 - 1.4 * t, energy_j={p: 0.1 * i * t for i, p in enumerate(PARTS)},
                      power_w={p: 0.1 * i for i, p in enumerate(PARTS)}, cpu_utilisation=0.2,
                      hosted={"Blob-1": "running", "Loc-1": "running"},
                      sources={"Blob-1": SourceStats(run=0, produced=int(t * 4), missed=0, produced_total=int(t * 4))},
                      sinks={"Loc-1": sink}, links={"laptop": True, "r2": True, "r3": False}, runs={"Blob-1": 7},
                      compute_ms={"Blob-1": 12.5}, queue_depth=0, errors={}, counters={"forwarded": 3},
                      depleted=False, acks_wanted=("Blob-1",), plan_leader="laptop:1", generations={"Blob-1": 2})
    return dataclasses.replace(base, **changes)


def sent(encoder: StatusEncoder, st_: NodeStatus) -> NodeStatus | StatusDelta:
    return decode(encoder.encode(st_), (NodeStatus, StatusDelta))


def test_after_a_keyframe_each_status_goes_as_its_change_and_a_receiver_rebuilds_it_exactly():
    encoder, receiver = StatusEncoder(), StatusAssembler()
    statuses = [status(0.5 * i) for i in range(8)]
    statuses[3] = dataclasses.replace(statuses[3], hosted={"Blob-1": "running"}, errors={"garbled": 1})
    kinds = []
    for st_ in statuses:
        payload = encoder.encode(st_)
        msg = decode(payload, (NodeStatus, StatusDelta))
        kinds.append(type(msg))
        assert receiver.whole(msg) == st_
    assert kinds == [NodeStatus] + [StatusDelta] * 7
    assert (encoder.keyframes, encoder.deltas, receiver.unapplied) == (1, 7, 0)
    # what repeats (stages, links, the parts' names, sinks' runs) is not sent again
    whole, delta = len(encode(statuses[5])), len(encoder.encode(status(4.0)))
    assert delta < 0.45 * whole, (delta, whole)
    # a map's key the keyframe has travels as its position; a key gone is named, by position, too
    msg = sent(encoder, status(4.5, hosted={"Blob-1": "running", "Map-1": "starting"}, links={"laptop": True, "r2": True}))
    assert isinstance(msg, NodeStatus)  # a link changed: whole (a node cut off missed the changes)
    msg = sent(encoder, status(5.0, hosted={"Map-1": "starting"}, links={"laptop": True, "r2": True}))
    assert isinstance(msg, StatusDelta)
    hosted = msg.changes[[f.name for f in dataclasses.fields(NodeStatus)].index("hosted")]
    assert hosted == [{}, [0]]  # Blob-1 (position 0) gone, Map-1 as it was


def test_a_lost_delta_costs_nothing_each_change_is_from_the_keyframe():
    encoder, receiver = StatusEncoder(), StatusAssembler()
    payloads = [encoder.encode(status(0.5 * i, counters={"forwarded": i})) for i in range(6)]
    assert receiver.whole(decode(payloads[0])) == status(0.0, counters={"forwarded": 0})
    # the second to the fifth lost: the sixth alone makes the whole status
    assert receiver.whole(decode(payloads[5])) == status(2.5, counters={"forwarded": 5})
    assert receiver.unapplied == 0


def test_without_its_keyframe_a_delta_waits_for_the_next_keyframe_then_the_view_is_exact():
    encoder, receiver = StatusEncoder(), StatusAssembler()
    first = encoder.encode(status(0.0))  # lost on the way
    deltas = [encoder.encode(status(0.5 * i)) for i in range(1, 4)]
    assert first and all(receiver.whole(decode(d)) is None for d in deltas)
    assert receiver.unapplied == 3
    # the next keyframe comes KEY_EVERY_S after the last at the latest
    later = status(KEY_EVERY_S + 0.1, plan_epoch=4)
    msg = sent(encoder, later)
    assert isinstance(msg, NodeStatus) and receiver.whole(msg) == later
    after = status(KEY_EVERY_S + 0.6, plan_epoch=4, runs={"Blob-1": 9})
    msg = sent(encoder, after)
    assert isinstance(msg, StatusDelta) and receiver.whole(msg) == after


def test_a_receiver_that_missed_a_keyframe_asks_for_one_and_has_the_view_within_a_status():
    """Sweep seed 1695: r1's keyframe (it said it had lost sight of r3) was lost on a lossy link, and
    the base station applied none of r1's next seven changes: for 10 s it took r3 for reachable
    through r1. The receiver names a sender whose keyframe it missed (`take_wanted`); asked, the
    sender's next status goes whole (the base station's view to it says `send_whole`)."""
    encoder, receiver = StatusEncoder(), StatusAssembler()
    assert receiver.whole(sent(encoder, status(0.0))) == status(0.0)
    lost = encoder.encode(status(1.0, links={"laptop": True, "r2": False, "r3": False}))  # its links changed
    assert isinstance(decode(lost), NodeStatus)  # so it went whole, and was lost on the way
    assert receiver.whole(sent(encoder, status(1.5, links={"laptop": True, "r2": False, "r3": False}))) is None
    assert receiver.take_wanted() == {"r1"} and receiver.take_wanted() == set()  # asked once per miss
    encoder.refresh()  # what the robot does on a view saying send_whole
    now = status(2.0, links={"laptop": True, "r2": False, "r3": False})
    assert receiver.whole(sent(encoder, now)) == now
    # an older change overtaken by a newer keyframe asks for nothing: the receiver has a newer one
    stale = StatusEncoder(key_every_s=2.0)
    k1 = stale.encode(status(0.0, node="r2"))
    d1 = stale.encode(status(1.0, node="r2", plan_epoch=9))
    k2 = stale.encode(status(2.5, node="r2", plan_epoch=9))
    receiver.whole(decode(k1))
    receiver.whole(decode(k2))
    assert receiver.whole(decode(d1)) is None and receiver.take_wanted() == set()


def test_an_older_delta_after_a_newer_keyframe_never_rolls_the_view_back():
    encoder, receiver = StatusEncoder(key_every_s=2.0), StatusAssembler()
    k1 = encoder.encode(status(0.0))
    d1 = encoder.encode(status(1.0, plan_epoch=9))  # a change from k1
    k2 = encoder.encode(status(2.5, plan_epoch=9))  # the next keyframe
    d2 = encoder.encode(status(3.0, plan_epoch=10))
    assert isinstance(decode(k2), NodeStatus) and isinstance(decode(d2), StatusDelta)
    assert receiver.whole(decode(k1)).plan_epoch == 3
    assert receiver.whole(decode(k2)).plan_epoch == 9
    assert receiver.whole(decode(d1)) is None  # from k1: the view stays k2's
    assert receiver.holds("r1") == 1002.5 and receiver.unapplied == 1
    assert receiver.whole(decode(d2)) == status(3.0, plan_epoch=10)
    # an older keyframe arriving late is handed on (the caller drops it by its t_unix) but never
    # becomes the base for what follows
    assert receiver.whole(decode(k1)) is not None and receiver.holds("r1") == 1002.5
    assert receiver.whole(decode(d2)) == status(3.0, plan_epoch=10)


def test_a_restarted_sender_starts_with_a_keyframe_its_old_deltas_no_longer_apply():
    old, receiver = StatusEncoder(), StatusAssembler()
    receiver.whole(decode(old.encode(status(0.0))))
    stale = old.encode(status(1.0, runs={"Blob-1": 8}))
    new = StatusEncoder()  # the restarted process
    first = status(5.0, hosted={}, runs={}, compute_ms={}, generations={})
    msg = sent(new, first)
    assert isinstance(msg, NodeStatus) and receiver.whole(msg) == first
    assert receiver.whole(decode(stale)) is None  # from the old process's keyframe
    assert receiver.whole(sent(new, dataclasses.replace(first, t_unix=1005.5))) == dataclasses.replace(first, t_unix=1005.5)


def test_a_keyframe_goes_when_asked_when_the_mission_changes_and_when_the_change_is_large():
    encoder = StatusEncoder()
    assert isinstance(sent(encoder, status(0.0)), NodeStatus)
    assert isinstance(sent(encoder, status(0.5)), StatusDelta)
    encoder.refresh()  # a base station began listening
    assert isinstance(sent(encoder, status(1.0)), NodeStatus)
    mission = MissionInfo(scenario="paper-fig7", accounting="paper", epoch_unix=999.0, speed=1.0,
                          energies_j={"r1": 64000.0, "r2": 64000.0})
    assert isinstance(sent(encoder, status(1.5, mission=mission)), NodeStatus)
    assert isinstance(sent(encoder, status(2.0, mission=mission)), StatusDelta)
    big = {f"Stage-{i}": "running" for i in range(40)}
    assert isinstance(sent(encoder, status(2.5, mission=mission, hosted=big)), NodeStatus)
    # one keyframe per t_unix (it names the keyframe): a status due whole at that time goes as a change
    encoder.refresh()
    assert isinstance(sent(encoder, status(2.5, mission=mission, hosted=big, plan_epoch=5)), StatusDelta)
    assert (encoder.keyframes, encoder.deltas) == (4, 3)


def test_each_sender_has_its_own_keyframe():
    a, b, receiver = StatusEncoder(), StatusEncoder(), StatusAssembler()
    receiver.whole(sent(a, status(0.0, node="r1")))
    receiver.whole(sent(b, status(0.0, node="r2", plan_epoch=7)))
    assert receiver.whole(sent(a, status(0.5, node="r1"))) == status(0.5, node="r1")
    assert receiver.whole(sent(b, status(0.5, node="r2", plan_epoch=7))) == status(0.5, node="r2", plan_epoch=7)
    small = StatusAssembler(max_senders=1)  # a bounded receiver forgets the earliest sender held
    small.whole(sent(StatusEncoder(), status(0.0, node="r1")))
    small.whole(sent(StatusEncoder(), status(0.0, node="r2")))
    assert small.holds("r1") is None and small.holds("r2") == 1000.0


def delta_payload(node: str, t_unix: float, key_t: float, changes) -> bytes:
    return msgpack.packb([b"AP", PROTOCOL_VERSION, "status-delta", [node, t_unix, key_t, changes]], use_bin_type=True)


NAMES = [f.name for f in dataclasses.fields(NodeStatus)]


@pytest.mark.parametrize("changes, why", [
    ({NAMES.index("node"): "r2"}, "no field"),  # speaking for another node through the changes
    ({NAMES.index("t_unix"): 5e9}, "no field"),  # its clock is the delta's own
    ({len(NAMES): 1}, "no field"),
    ({-1: 1}, "no field"),
    ({NAMES.index("plan_epoch"): "three"}, "expected int"),
    ({NAMES.index("battery_j"): float("nan")}, "finite"),
    ({NAMES.index("hosted"): {"Blob-1": "running"}}, r"expected \[entries"),
    ({NAMES.index("hosted"): [{}, [7]]}, "no key at position"),
    ({NAMES.index("hosted"): [{9: "running"}, []]}, "no key at position"),
    ({NAMES.index("hosted"): [{b"x": "running"}, []]}, "expected str"),
    ({NAMES.index("hosted"): [{}, ["Blob-1"]]}, "no key at position"),
    ({NAMES.index("sinks"): [{0: [1, 2]}, []]}, "expected"),
])
def test_a_garbled_delta_is_refused_and_the_view_stays_whole(changes, why):
    encoder, receiver = StatusEncoder(), StatusAssembler()
    first = status(0.0)
    receiver.whole(sent(encoder, first))
    with pytest.raises(ProtocolError, match=why):
        receiver.whole(decode(delta_payload("r1", 1000.5, 1000.0, changes), (NodeStatus, StatusDelta)))
    # and the next good one applies as if nothing had come
    assert receiver.whole(sent(encoder, status(1.0))) == status(1.0)


@pytest.mark.parametrize("payload", [
    msgpack.packb([b"AP", PROTOCOL_VERSION, "status-delta", ["r1", 1000.5, 1000.0, {"3": 4}]]),  # field by name
    msgpack.packb([b"AP", PROTOCOL_VERSION, "status-delta", ["r1", 1000.5, 1000.0]]),  # a field short
    msgpack.packb([b"AP", PROTOCOL_VERSION, "status-delta", ["r1", 1000.5, "k", {}]]),
    msgpack.packb([b"AP", PROTOCOL_VERSION, "status-delta", ["r1", 1000.5, 1000.0, {True: 4}]]),
])
def test_a_delta_of_the_wrong_shape_does_not_decode(payload):
    with pytest.raises(ProtocolError):
        decode(payload, (NodeStatus, StatusDelta))


def test_a_queued_delta_gives_way_to_a_newer_one_a_keyframe_never_does():
    # the base station's queue (`BaseStation._newest_only`): a robot's newest change from its
    # keyframe replaces the one still queued; a keyframe waits its turn, and the change after it finds it
    encoder = StatusEncoder()
    k1, d1, d2 = (encoder.encode(status(t)) for t in (0.0, 0.5, 1.0))
    assert not replaces_queued(k1) and replaces_queued(d1)
    q = EventQueue(newest_only=lambda key, payload: replaces_queued(payload))
    for payload in (k1, d1, d2):
        q.on_message("status/r1", payload)
    assert q.superseded == 1
    receiver = StatusAssembler()
    got = [receiver.whole(decode(q.get(0).payload)) for _ in range(2)]
    assert got == [status(0.0), status(1.0)] and q.get(0) is None


def test_the_base_station_queues_statuses_by_that_rule():
    from autopower.basestation.process import BaseStation
    from autopower.protocol import Keys

    station = BaseStation.__new__(BaseStation)
    station.keys = Keys("t")
    encoder = StatusEncoder()
    k1, d1 = encoder.encode(status(0.0)), encoder.encode(status(0.5))
    keys = station.keys
    assert not station._newest_only(keys.status("r1"), k1) and station._newest_only(keys.status("r1"), d1)
    assert station._newest_only(keys.addressed("laptop", "r1"), b"ack")
    assert not station._newest_only(keys.inbox, d1)


parts = st.sampled_from(PARTS + ("bluetooth:send", "bluetooth:receive"))
floats = st.floats(min_value=0.0, max_value=1e6, allow_nan=False)
maps_of_floats = st.dictionaries(parts, floats, max_size=6)
stages = st.dictionaries(st.sampled_from(["Blob-1", "Blob-2", "Loc-1", "Map-1"]),
                         st.sampled_from(["starting", "running", "stopping"]), max_size=4)
links = st.dictionaries(st.sampled_from(["laptop", "r2", "r3", "r4"]), st.booleans(), max_size=4)
counters = st.dictionaries(st.sampled_from(["forwarded", "custody-frames", "custody-bytes", "held-outputs"]),
                           st.integers(min_value=0, max_value=2**40), max_size=4)
changed = st.fixed_dictionaries({}, optional={
    "energy_j": maps_of_floats, "power_w": maps_of_floats, "hosted": stages, "links": links, "counters": counters,
    "errors": counters, "plan_epoch": st.integers(min_value=-1, max_value=50), "battery_j": st.none() | floats,
    "acks_wanted": st.lists(st.sampled_from(["Blob-1", "Loc-1"]), max_size=2).map(tuple),
    "failed": st.dictionaries(st.sampled_from(["Blob-1", "Map-1"]), st.text(max_size=8), max_size=2),
    "down": st.none() | st.tuples(floats, floats), "generations": st.dictionaries(st.sampled_from(["Blob-1", "Loc-1"]),
                                                                                 st.integers(0, 9), max_size=2),
})


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(changed, st.floats(min_value=0.01, max_value=4.0), st.booleans()), min_size=1, max_size=25))
def test_any_series_of_statuses_with_any_losses_gives_a_receiver_either_nothing_or_exactly_what_was_sent(steps):
    """A receiver's view after each status is what the sender built (the status arrived, or a later
    one), or nothing new (a change from a keyframe it lost): never anything else."""
    encoder, receiver = StatusEncoder(), StatusAssembler()
    t, current, view = 0.0, status(0.0), None
    for fields, dt, lost in steps:
        t += dt
        current = dataclasses.replace(current, t_virtual=t, t_unix=1000.0 + t, **fields)
        payload = encoder.encode(current)
        if lost:
            continue
        got = receiver.whole(decode(payload, (NodeStatus, StatusDelta)))
        if got is not None:
            assert got == current
            view = got
        else:
            assert isinstance(decode(payload), StatusDelta)
    assert view is None or view.t_unix <= current.t_unix
    assert encoder.keyframes >= 1 and encoder.keyframes + encoder.deltas == len(steps)
