"""A relayed `Packet` read without its body, and the next hop's copy spliced around that body.

A node on a packet's route only needs the header (path, media, hop, what to charge) and must pass
the body on untouched. The strict codec builds the whole message (the body copied out, every
field checked through the type hints) and encodes it again (the body copied twice more): for a
230 KB camera frame that is most of what a relay costs. Here:

- `read_header` reads the header of a packet in the codec's own layout (`encode` writes the
  fields as an array in declaration order, ``body`` last) and checks it exactly as `decode(data, Packet)`
  would (types, finiteness, the `Packet` invariants); it never copies the body, only notes where
  it starts. Anything it does not recognise gives None, and the caller hands the bytes to the
  strict codec, which decides (and counts) what they are: this reader may refuse what the codec
  would accept, never the other way round (tests/unit/test_forwarding.py holds it to that).
- `forwarded` is the packet with ``hop + 1``, byte for byte what `encode` would write for it: the
  re-encoded header followed by the received body bytes, one copy.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import msgpack

from autopower.protocol.codec import MAGIC, PROTOCOL_VERSION
from autopower.protocol.messages import Packet

KIND = Packet.KIND
HEADER_FIELDS = ("path", "media", "hop", "charge_bytes", "weight", "purpose", "chain")  # then "body"
MAX_HEADER = 4096  # bytes: a path of a few node names; a longer header goes to the strict codec
MAX_BODY = 64 * 2**20  # the codec's max_bin_len
_BIN = {0xC4: 1, 0xC5: 2, 0xC6: 4}  # msgpack bin 8/16/32: length bytes after the type byte
_EMPTY_BIN = msgpack.packb(b"", use_bin_type=True)


class PacketHeader(NamedTuple):
    path: tuple[str, ...]
    media: tuple[str, ...]
    hop: int
    charge_bytes: int
    weight: float
    purpose: str
    chain: str
    body_at: int  # offset of the body's msgpack bin header in the packet's bytes


def _strings(value) -> bool:
    return type(value) is list and all(type(v) is str for v in value)


def read_header(data: bytes) -> PacketHeader | None:
    """The header of an encoded `Packet`, checked as strictly as the codec; None: ask the codec."""
    size = len(data)
    # Walk the message up to the body (the last field: a bin that ends the message), then decode what
    # precedes it with an empty bin in its place: the codec would read the same fields from
    # ``data``, and the body from where it is.
    walk = msgpack.Unpacker(raw=False, strict_map_key=False)
    walk.feed(bytes(data[:MAX_HEADER]))
    try:
        if walk.read_array_header() != 4:
            return None
        for _ in range(3):  # the magic, the version, the kind: `_read_fields` checks them
            walk.skip()
        if walk.read_array_header() != len(HEADER_FIELDS) + 1:
            return None
        for _ in HEADER_FIELDS:
            walk.skip()
        body_at = walk.tell()
    except Exception:  # garbage, or a header longer than MAX_HEADER: the strict codec says which
        return None
    width = _BIN.get(data[body_at]) if body_at < size else None
    if width is None:
        return None
    length = int.from_bytes(data[body_at + 1:body_at + 1 + width], "big")
    if body_at + 1 + width + length != size or length > MAX_BODY:
        return None
    return _read_fields(bytes(data[:body_at]))


@lru_cache(maxsize=256)  # a relay sees a handful of distinct headers (chain, route, hop), packet after packet
def _read_fields(head: bytes) -> PacketHeader | None:
    """The header from the bytes before the body's bin (the same bytes, the same answer)."""
    body_at = len(head)
    try:
        message = msgpack.unpackb(head + _EMPTY_BIN, raw=False, strict_map_key=False)
    except Exception:  # msgpack raises many unrelated types on garbage: the strict codec says which
        return None
    if type(message) is not list or len(message) != 4:
        return None
    magic, version, kind, fields = message
    if (magic != MAGIC or type(version) is not int or version != PROTOCOL_VERSION or kind != KIND
            or type(fields) is not list or len(fields) != len(HEADER_FIELDS) + 1 or fields[-1] != b""):
        return None
    path, media, hop, charge_bytes, weight, purpose, chain, _ = fields
    # the codec's checks for these hints: int excludes bool, a float field takes an int, finite only
    if (not _strings(path) or not _strings(media) or type(hop) is not int or type(charge_bytes) is not int
            or type(purpose) is not str or type(chain) is not str):
        return None
    if type(weight) is not float:
        if type(weight) is not int:
            return None
        try:
            weight = float(weight)
        except OverflowError:
            return None
    if not math.isfinite(weight) or Packet.problem(path, media, hop, charge_bytes, weight, purpose) is not None:
        return None
    return PacketHeader(tuple(path), tuple(media), hop, charge_bytes, weight, purpose, chain, body_at)


def forwarded(data: bytes, header: PacketHeader) -> bytes:
    """``data`` (the packet ``header`` was read from) with ``hop + 1``: what `encode` writes for it."""
    return b"".join((_next_head(header), memoryview(data)[header.body_at:]))


@lru_cache(maxsize=256)
def _next_head(header: PacketHeader) -> bytes:
    """The next hop's encoding up to the body's bin."""
    fields = [list(header.path), list(header.media), header.hop + 1, header.charge_bytes, header.weight,
              header.purpose, header.chain, b""]
    return msgpack.packb([MAGIC, PROTOCOL_VERSION, KIND, fields], use_bin_type=True)[:-len(_EMPTY_BIN)]
