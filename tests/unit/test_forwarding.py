"""A relayed packet's header read without its body: never more lenient than the codec, and the
next hop's copy is byte for byte what `encode` writes."""

from __future__ import annotations

import dataclasses

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.errors import ProtocolError
from autopower.protocol import PROTOCOL_VERSION, ChainFrame, Packet, decode, encode
from autopower.protocol.forwarding import forwarded, read_header


def packet(size: int = 200, **changes) -> Packet:
    frame = ChainFrame(chain="Blob-2", run=0, seq=7, target=1, t_virtual=1.5, t_unix=2.5, payload_len=size,
                       payload=bytes(range(256)) * (size // 256) + bytes(size % 256))
    fields = dict(path=("r3", "r1", "laptop"), media=("802.11a", "802.11b"), hop=1, charge_bytes=size,
                  weight=2.5, purpose="chain", chain="Blob-2", body=encode(frame))
    return Packet(**{**fields, **changes})


def raw(fields: dict) -> bytes:
    """The packet a sender would put: ``fields`` in `Packet`'s order when they are its fields, else
    the values as given (too many, too few)."""
    names = [f.name for f in dataclasses.fields(Packet)]
    values = [fields[n] for n in names] if set(fields) == set(names) else list(fields.values())
    return msgpack.packb([b"AP", PROTOCOL_VERSION, "packet", values], use_bin_type=True)


def fields_of(p: Packet) -> dict:
    return {f.name: (list(v) if isinstance(v := getattr(p, f.name), tuple) else v) for f in dataclasses.fields(p)}


@pytest.mark.parametrize("size", [0, 100, 200, 1059, 70_000, 230_415])  # bin 8, 16 and 32 bodies
def test_the_header_is_what_the_codec_reads_and_the_forwarded_copy_is_what_encode_writes(size):
    p = packet(size)
    data = encode(p)
    header = read_header(data)
    assert header is not None
    assert (header.path, header.media, header.hop, header.charge_bytes, header.weight, header.purpose,
            header.chain) == (p.path, p.media, p.hop, p.charge_bytes, p.weight, p.purpose, p.chain)
    assert data[header.body_at:].endswith(p.body)
    assert forwarded(data, header) == encode(dataclasses.replace(p, hop=2))
    assert decode(forwarded(data, header), Packet).body == p.body  # the body crossed untouched


def test_a_chain_named_body_and_an_integer_weight_read_as_the_codec_reads_them():
    p = packet(chain="body", path=("body", "r1", "body"))
    header = read_header(encode(p))
    assert header is not None and header.chain == "body"
    fields = fields_of(packet())
    fields["weight"] = 3  # the codec takes an int for a float field
    header = read_header(raw(fields))
    assert header is not None and header.weight == 3.0 and type(header.weight) is float
    assert decode(raw(fields), Packet).weight == 3.0


@pytest.mark.parametrize("change", [
    {"hop": True}, {"hop": 1.0}, {"hop": 0}, {"hop": 3}, {"charge_bytes": -1}, {"weight": float("nan")},
    {"weight": float("inf")}, {"weight": -1.0}, {"weight": "1"}, {"purpose": "gossip"}, {"path": ["r3", "r1"]},
    {"path": ["r3", 1, "laptop"]}, {"media": ("802.11a",)}, {"chain": None}, {"body": "text"},
])
def test_a_header_the_codec_refuses_is_refused(change):
    fields = {**fields_of(packet()), **change}
    data = raw(fields)
    with pytest.raises(ProtocolError):
        decode(data, Packet)
    assert read_header(data) is None


@pytest.mark.parametrize("mangle", [
    lambda f: raw({**f, "extra": 1}),  # an unknown field
    lambda f: raw({k: v for k, v in f.items() if k != "hop"}),  # a missing one
    lambda f: msgpack.packb([b"AP", PROTOCOL_VERSION + 1, "packet", list(f.values())], use_bin_type=True),
    lambda f: msgpack.packb([b"XX", PROTOCOL_VERSION, "packet", list(f.values())], use_bin_type=True),
    lambda f: msgpack.packb([b"AP", PROTOCOL_VERSION, "frame", list(f.values())], use_bin_type=True),
    lambda f: msgpack.packb([b"AP", PROTOCOL_VERSION, "packet", f], use_bin_type=True),  # version 2's map
    lambda f: raw(f) + b"\x00",  # trailing bytes
    lambda f: raw(f)[:-1],  # cut short
])
def test_what_is_not_a_packet_is_not_read(mangle):
    data = mangle(fields_of(packet()))
    with pytest.raises(ProtocolError):
        decode(data, Packet)
    assert read_header(data) is None


def test_a_header_longer_than_the_reader_looks_is_left_to_the_codec():
    from autopower.protocol.forwarding import MAX_HEADER

    long = packet(chain="Blob-2" + "x" * MAX_HEADER)
    assert decode(encode(long), Packet) == long  # valid: the codec takes it (on the loop)
    assert read_header(encode(long)) is None  # the reader walks MAX_HEADER bytes at most


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(size=st.sampled_from([0, 10, 300, 70_000]), flips=st.lists(
    st.tuples(st.integers(min_value=0, max_value=400), st.integers(min_value=0, max_value=255)), min_size=1,
    max_size=4), cut=st.integers(min_value=0, max_value=3))
def test_mangled_packets_are_read_only_if_the_codec_reads_them_the_same(size, flips, cut):
    data = bytearray(encode(packet(size)))
    for position, byte in flips:  # mostly the header: that is what the reader parses
        data[position % len(data)] = byte
    data = bytes(data[:len(data) - cut] if cut < 3 else data + b"\x00")
    header = read_header(data)
    if header is None:
        return
    p = decode(data, Packet)  # never more lenient: what the reader takes, the codec takes
    assert (header.path, header.media, header.hop, header.charge_bytes, header.weight, header.purpose,
            header.chain) == (p.path, p.media, p.hop, p.charge_bytes, p.weight, p.purpose, p.chain)
    if header.hop < len(header.path) - 1:
        assert forwarded(data, header) == encode(dataclasses.replace(p, hop=p.hop + 1))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=600))
def test_random_bytes_are_not_read(data):
    header = read_header(data)
    if header is not None:  # (practically never) only if it is a packet
        decode(data, Packet)
