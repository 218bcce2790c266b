"""The wire protocol: every message round-trips, and anything malformed is a ProtocolError."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import pytest
from hypothesis import given, settings, strategies as st

from autopower.errors import ProtocolError
from autopower.protocol import (
    PROTOCOL_VERSION,
    Ack,
    Assign,
    AutoCommand,
    Batch,
    ChainCommand,
    ChainFrame,
    Consumed,
    Keys,
    LinkCommand,
    LinkInfo,
    MigrateCommand,
    MigrateOut,
    MissionInfo,
    NodeStatus,
    OperatorReply,
    Packet,
    PeerStatus,
    PlanChange,
    PlanUpdate,
    Prepare,
    Prepared,
    Relayed,
    Release,
    SinkStats,
    SnapshotRequest,
    SourceStats,
    StageFailed,
    StageReady,
    StateTransfer,
    StatusDelta,
    SubgroupDecision,
    SubgroupMove,
    SubgroupPropose,
    SubgroupVote,
    decode,
    encode,
    message_kinds,
)
from autopower.protocol.codec import looks_like_message, message_kind

FRAME = ChainFrame(chain="Blob-2", run=1, seq=7, target=0, t_virtual=1.75, t_unix=1.7e9, payload_len=3,
                   payload=b"abc\0\0")
MISSION = MissionInfo(scenario="paper-fig7", accounting="paper", epoch_unix=1.7e9, speed=10.0,
                      energies_j={"r1": 64000.0})

SAMPLES = [
    FRAME,
    Packet(path=("r2", "r1", "laptop"), media=("bluetooth", "802.11a"), hop=1, charge_bytes=230415, weight=0.25,
           purpose="chain", chain="Blob-2", body=encode(FRAME)),
    StateTransfer(stage="Loc-2", generation=4, chain="Loc-2", run=0, state=b"\x01" * 100, next_seq=None,
                  pending=(FRAME,), t_export_unix=1.0, from_node="r2"),
    Assign(stage="Loc-1", generation=1, chain="Loc-1", run=0, resume_seq=0),
    Prepare(stage="Loc-1", generation=2, from_node="r1"),
    MigrateOut(stage="Loc-1", generation=2, to_node="laptop"),
    Release(stage="Loc-1", generation=3),
    Prepared(stage="Loc-1", generation=2, node="laptop"),
    StageReady(stage="Loc-1", generation=2, node="laptop", imported_state=True, resume_seq=5, downtime_ms=3.5,
               buffered=1),
    PlanUpdate(epoch=3, mission=MISSION, placement={"Loc-1": "laptop"}, running={"Loc-1": 0},
               links=(LinkInfo(a="r1", b="laptop", medium="802.11a"),), predicted_w={"r1": 1.35},
               predicted_lifetime_s=None, plan_t_virtual=0.0),
    PlanChange(epoch=4, incarnation=0, leader="laptop:1", base_epoch=3, base_digest=b"\x01" * 16,
               digest=b"\x02" * 16, placement={"Loc-1": "r1"}, unplaced=("Loc-2",), running={}, not_running=(),
               links=(), links_gone=(LinkInfo(a="r1", b="r2", medium="bluetooth"),), predicted_w={"r1": 1.5}, not_predicted=(), levels={}, not_levelled=(), variants={},
               not_varied=(), predicted_lifetime_s=None, plan_t_virtual=1.0, policy=None, reasons=("a link cut",),
               operator=None),
    STATUS := NodeStatus(node="r1", t_virtual=3.0, t_unix=1.0, plan_epoch=3, initial_j=64000.0, battery_j=63990.0,
               energy_j={"cpu_idle": 10.0}, power_w={"cpu_idle": 1.34}, cpu_utilisation=0.0,
               hosted={"Loc-1": "running"},
               sources={"Loc-1": SourceStats(run=0, produced=2, missed=0, produced_total=2)},
               sinks={"Loc-1": SinkStats(run=0, received=2, duplicates=0, contiguous=2, max_seq=1, stale=0,
                                         latency_ms_p50=1.0, latency_ms_max=2.0, received_total=2,
                                         duplicates_total=0, digest=12345)},
               links={"laptop": True}, runs={}, compute_ms={}, queue_depth=0, errors={}, counters={},
               depleted=False, acks_wanted=("Blob-1", "Loc-1"), process=1 << 62 | 7, resumed={"Loc-1": 0}),
    PeerStatus.of(STATUS),
    StatusDelta(node="r1", t_unix=1.5, key_t=1.0, changes={1: 3.5, 5: 63989.0, 7: [{0: 10.5, "cpu_busy": 0.1}, []]}),
    ACK := Ack(node="laptop", t_unix=1.5, queue_wait_s=0.25,
        consumed={"Blob-2#1": Consumed(run=0, generation=2, next_seq=4, max_seq=20, missing=((4, 6), (9, 9)))}),
    ChainCommand(chain="Blob-2", enabled=False),
    MigrateCommand(stage="Loc-2", to_node="r1"),
    AutoCommand(),
    LinkCommand(node="r3", laptop_robot="gsm", robot_robot="bluetooth"),
    SnapshotRequest(),
    OperatorReply(ok=True, message="ok", snapshot={"a": [1, 2.5, None, {"b": "c"}]}),
    Relayed(path=("laptop", "r2", "r1"), hop=1, key="autopower/t/node/r1/control", payload=b"x"),
    SubgroupPropose(round_id="r1-1", leader="r1", members=("r1", "r2"), placement={"Loc-1": "r1"},
                    moves=(SubgroupMove(stage="Loc-1", from_node=None, to_node="r1"),), generation=7, reason="x"),
    SubgroupVote(round_id="r1-1", node="r2", accept=True, reason=""),
    SubgroupDecision(round_id="r1-1", commit=True, reason="all accepted"),
    StageFailed(stage="Motion-1", generation=3, node="r2", what="raised", detail="run(seq 7): ValueError: bad frame",
                running=False),
    Batch(items=(b"\x94\xa2AP", b"")),  # its items are checked by `unbatch`, not by the codec
]


def test_every_kind_has_a_sample():
    assert {type(m).KIND for m in SAMPLES} == set(message_kinds())


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).KIND)
def test_round_trip(msg):
    assert decode(encode(msg)) == msg
    assert looks_like_message(encode(msg))  # the cheap check before queuing never refuses ours


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).KIND)
def test_a_messages_kind_reads_from_its_header_alone(msg):
    data = encode(msg)
    assert message_kind(data) == type(msg).KIND
    assert message_kind(data[:len(data) // 2 + 8]) in (type(msg).KIND, None)  # never a wrong kind


def test_what_is_not_a_message_has_no_kind():
    for data in (b"", b"\x94", b"\xc1" * 10, _raw("frame", {}, magic=b"XX"), msgpack.packb([1, 2, 3, 4]),
                 _raw(7, {})):
        assert message_kind(data) is None


def test_what_does_not_look_like_a_message_never_decodes():
    assert looks_like_message(_raw("frame", {}, version=99))  # decode says which version it is
    for data in (b"", b"\x94", b"\xc1" * 10, _raw("frame", {}, magic=b"XX"), msgpack.packb([1, 2, 3, 4])):
        assert not looks_like_message(data)
        with pytest.raises(ProtocolError):
            decode(data)


def _raw(kind, fields, version=PROTOCOL_VERSION, magic=b"AP"):
    """A message as a sender would put it; ``fields`` by name (a dict of exactly the class's fields,
    put in its order, as `encode` does; any other dict goes as its values in their order) or as
    they go on the wire (a list)."""
    cls = message_kinds().get(kind)
    if isinstance(fields, dict) and cls is not None:
        names = [f.name for f in dataclasses.fields(cls)]
        fields = [fields[n] for n in names] if set(fields) == set(names) else list(fields.values())
    return msgpack.packb([magic, version, kind, fields], use_bin_type=True)


def _fields(msg) -> dict:
    """A message's wire fields by name (each value as the wire carries it)."""
    names = [f.name for f in dataclasses.fields(msg)]
    return dict(zip(names, msgpack.unpackb(encode(msg), raw=False)[3], strict=True))


def test_fields_go_on_the_wire_by_position_without_their_names():
    status = next(m for m in SAMPLES if isinstance(m, NodeStatus))
    wire = msgpack.unpackb(encode(status), raw=False, strict_map_key=False)
    assert wire[:3] == [b"AP", PROTOCOL_VERSION, "status"] and isinstance(wire[3], list)
    assert b"battery_j" not in encode(status) and b"received" not in encode(status)  # no name, nested or not
    assert len(wire[3]) == len(dataclasses.fields(NodeStatus))


@pytest.mark.parametrize("data, match", [
    (b"", "msgpack"),
    (b"\xc1", "msgpack"),
    (msgpack.packb({"a": 1}), "not an AutoPower message"),
    (msgpack.packb([b"AP", 1, "frame"]), "not an AutoPower message"),
    (_raw("frame", {}, magic=b"XX"), "magic"),
    (_raw("frame", {}, version=PROTOCOL_VERSION + 1), "protocol version"),
    (_raw("no-such-kind", {}), "unknown message kind"),
    (_raw(7, {}), "kind must be a string"),
    (msgpack.packb([b"AP", PROTOCOL_VERSION, "frame", {"chain": "x"}]), "as a list, got dict"),  # version 2's form
    (_raw("release", {"stage": "x"}), r"expected 2 fields \(stage, generation\), got 1"),
    (_raw("release", {"stage": "x", "generation": 1, "extra": 2}), "expected 2 fields"),
    (_raw("release", {"stage": "x", "generation": "1"}), "expected int"),
    (_raw("release", {"stage": "x", "generation": True}), "expected int"),
    (_raw("release", {"stage": 5, "generation": 1}), "expected str"),
    (_raw("stage-ready", {**_fields(SAMPLES[8]), "downtime_ms": math.nan}), "NaN"),
    (_raw("stage-ready", {**_fields(SAMPLES[8]), "downtime_ms": math.inf}), "not a finite number"),
    (_raw("stage-ready", {**_fields(SAMPLES[8]), "downtime_ms": -math.inf}), "not a finite number"),
    (_raw("packet", {**_fields(SAMPLES[1]), "hop": 5}), "hop"),
    (_raw("packet", {**_fields(SAMPLES[1]), "media": ["bluetooth"]}), "medium per hop"),
    (_raw("frame", {**_fields(FRAME), "payload_len": 99}), "exceeds"),
    (_raw("state", {**_fields(SAMPLES[2]), "pending": [["x"]]}), "expected .* fields"),
    (_raw("plan", {**_fields(SAMPLES[9]), "links": [["r1", "laptop"]]}), "expected 3 fields"),
    # which process sent a status, and the source positions it resumed: what a base station's
    # decision to go on in a chain's run rests on (`basestation.runs`)
    (_raw("status", {**_fields(STATUS), "process": -1}), "process"),
    (_raw("status", {**_fields(STATUS), "process": 2**63}), "process"),
    (_raw("status", {**_fields(STATUS), "process": 1.5}), "expected int"),
    (_raw("status", {**_fields(STATUS), "resumed": {"Blob-2": 0}}), "not a run of a source"),
    (_raw("status", {**_fields(STATUS), "resumed": {"Loc-1": -1}}), "not a run of a source"),
    (_raw("status", {**_fields(STATUS), "resumed": {"Loc-1": "0"}}), "expected int"),
    (_raw("status", {**_fields(STATUS), "resumed": [["Loc-1", 0]]}), "expected a map"),
    *[(_raw("ack", {**_fields(ACK), "consumed": {"Blob-2#1": [0, 1, 4, 20, missing]}}), match)
      for missing, match in (([[6, 5]], "not sorted"), ([[2, 5]], "within"), ([[8, 9], [4, 5]], "not sorted"),
                             ([[4, 5], [6, 7]], "disjoint"), ([[4, 21]], "within"),
                             ([[2 * i + 4, 2 * i + 4] for i in range(300)], "at most 256"),
                             ([4, 5], "expected"))],
])
def test_strict_rejection(data, match):
    with pytest.raises(ProtocolError, match=match):
        decode(data)


def test_an_optional_field_that_is_wrong_is_named_once():
    status = next(m for m in SAMPLES if isinstance(m, NodeStatus))
    for field, value, said in (("model_w", "a", "status.model_w: expected float, got str"),
                               ("down", [3.0], "status.down: expected 2 items, got 1")):
        with pytest.raises(ProtocolError) as caught:
            decode(_raw("status", {**_fields(status), field: value}))
        assert str(caught.value) == said


def test_non_finite_numbers_are_refused_at_the_sender_too():
    bad = dataclasses.replace(SAMPLES[8], downtime_ms=math.inf)
    with pytest.raises(ProtocolError, match="non-finite"):
        encode(bad)


def test_expect_limits_kinds():
    with pytest.raises(ProtocolError, match="not accepted here"):
        decode(encode(SAMPLES[3]), Packet)
    assert decode(encode(SAMPLES[3]), (Assign, Release)) == SAMPLES[3]


def test_encode_refuses_non_messages():
    with pytest.raises(ProtocolError):
        encode({"kind": "frame"})
    with pytest.raises(ProtocolError):
        encode(LinkInfo(a="a", b="b", medium="gsm"))  # a struct, not a message


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_never_escape_as_other_errors(data):
    try:
        decode(data)
    except ProtocolError:
        pass
    else:
        assert looks_like_message(data)


json_values = st.recursive(st.none() | st.booleans() | st.integers(-2**63, 2**63 - 1) | st.text(max_size=8)
                           | st.binary(max_size=8),
                           lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner,
                                                                                       max_size=3),
                           max_leaves=10)


@settings(max_examples=300, deadline=None)
@given(kind=st.sampled_from(sorted(message_kinds())), fields=st.lists(json_values, max_size=8))
def test_random_fields_for_every_kind_are_rejected_or_valid(kind, fields):
    try:
        msg = decode(_raw(kind, fields))
    except ProtocolError:
        return
    assert decode(encode(msg)) == msg  # whatever is accepted is a well-formed message


@settings(max_examples=200, deadline=None)
@given(chain=st.text(min_size=1, max_size=10), run=st.integers(0, 2**31), seq=st.integers(0, 2**62),
       target=st.integers(0, 9), t=st.floats(allow_nan=False, allow_infinity=False),
       payload=st.binary(max_size=64), padding=st.integers(0, 16))
def test_frame_round_trip_property(chain, run, seq, target, t, payload, padding):
    frame = ChainFrame(chain=chain, run=run, seq=seq, target=target, t_virtual=t, t_unix=t, payload_len=len(payload),
                       payload=payload + bytes(padding))
    back = decode(encode(frame))
    assert back == frame and back.data() == payload


def test_keys():
    keys = Keys("team-1")
    assert keys.node_data("r1") == "autopower/team-1/node/r1/data"
    assert keys.node_of_alive(keys.alive("r2")) == "r2"
    assert keys.node_of_alive("autopower/team-1/alive/r2/x") is None
    assert keys.node_of_status(keys.status("laptop")) == "laptop"
    for bad in ("a/b", "*", "", "r$1"):
        with pytest.raises(ValueError):
            Keys(bad)
        with pytest.raises(ValueError):
            keys.node_data(bad)


# ---- the compiled fast path decides exactly as the field-by-field checks do ---------------------
ODD = [None, True, False, 0, -1, 2**64 - 1, -2**63, 1.5, float("nan"), float("inf"), -float("inf"), "", "x", b"", b"x", [], ["x"],
       [1, 2], [[1, "a"]], {}, {"x": 1}, {"x": 1.5}, {1: "x"}, {"x": None}, {"x": [None, "a"]}, {"x": {"a": 1}}]


def _slow(kind: str, fields) -> object:
    """What the field-by-field decoder alone makes of ``fields`` (the value, or its error text)."""
    from autopower.protocol import codec

    try:
        return codec._build(message_kinds()[kind], fields, kind)
    except ProtocolError as exc:
        return f"error: {exc}"


def _fast(kind: str, fields) -> object:
    try:
        return decode(_raw(kind, fields))
    except ProtocolError as exc:
        return f"error: {exc}"


def _same(a, b) -> bool:
    # by repr: every field with its exact type (1 is not 1.0) and NaN where `Any` lets it through
    return type(a) is type(b) and repr(a) == repr(b)


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: m.KIND)
def test_fast_decoding_matches_the_field_by_field_checks(msg):
    """Every field of every sample swapped for odd values (and nested values too): the same message
    or the same error, word for word, as the field-by-field decoder that names where it is wrong."""
    fields = msgpack.unpackb(encode(msg), raw=False, strict_map_key=False)[3]
    cases = [fields, [*fields, 1], fields[1:]]

    def with_(at: int, value) -> list:
        return [*fields[:at], value, *fields[at + 1:]]

    for at, value in enumerate(fields):
        cases += [with_(at, odd) for odd in ODD]
        if isinstance(value, dict) and value:  # a nested map: its first entry made odd
            inner = next(iter(value))
            cases += [with_(at, {**value, inner: odd}) for odd in ODD]
            if isinstance(value[inner], list) and value[inner]:  # a struct in it: its first field
                cases += [with_(at, {**value, inner: [odd, *value[inner][1:]]}) for odd in ODD]
        if isinstance(value, list) and value:  # a struct or a list: its first item made odd
            cases += [with_(at, [odd] + value[1:]) for odd in ODD]
            if isinstance(value[0], list) and value[0]:
                cases += [with_(at, [[odd, *value[0][1:]], *value[1:]]) for odd in ODD]
    for case in cases:
        slow, fast = _slow(msg.KIND, case), _fast(msg.KIND, case)
        assert _same(slow, fast), (case, slow, fast)


@settings(max_examples=300, deadline=None)
@given(kind=st.sampled_from(sorted(message_kinds())), fields=st.lists(json_values, max_size=8))
def test_fast_decoding_matches_on_random_fields(kind, fields):
    assert _same(_slow(kind, fields), _fast(kind, fields))


def test_only_chain_frames_ride_below_the_control_plane():
    """Zenoh drains a higher priority first: statuses, acks and plans must not wait behind frames."""
    from autopower.protocol.keys import Keys, carries_chain_data

    keys = Keys("t1")
    assert carries_chain_data(keys.node_data("r1"), True)
    assert carries_chain_data(keys.node_relay("r1"), True)  # relayed frames keep their order with the rest
    control = [(keys.node_relay("r1"), False), (keys.node_control("r1"), True), (keys.status("r1"), False),
               (keys.peer("r1"), False), (keys.addressed("r1", "r2"), False), (keys.addressed("data", "data"), False),
               (keys.plan, True), (keys.subgroup, True), (keys.inbox, True), ("other/t1/node/r1/data", True)]
    assert not [k for k, reliable in control if carries_chain_data(k, reliable)]
