"""Batches: several messages for one key in one put (`Batch`).

`batched` makes the put: one payload goes as it is, several as a `Batch`. `unbatch` takes one
apart on the receiving side: every item must decode as one of the kinds accepted on that key, and
a batch inside a batch, an empty batch or one over `MAX_BATCH_ITEMS` is refused. It decodes every
item before it returns any, so a batch with one bad item is refused whole: a receiver never acts
on half of what a sender meant as one.
"""

from __future__ import annotations

from typing import Any

from autopower.errors import ProtocolError
from autopower.protocol.codec import decode, encode, message_kind
from autopower.protocol.messages import Batch

MAX_BATCH_ITEMS = 4096  # orders for one node in one reconcile: one per stage it gains, loses or moves


def batched(payloads: list[bytes]) -> bytes:
    """One put for ``payloads`` (at least one): the payload itself, or a `Batch` of them."""
    if not payloads:
        raise ValueError("nothing to send")
    if len(payloads) == 1:
        return payloads[0]
    if len(payloads) > MAX_BATCH_ITEMS:
        raise ValueError(f"{len(payloads)} messages in one batch; at most {MAX_BATCH_ITEMS}")
    return encode(Batch(items=tuple(payloads)))


def unbatch(payload: bytes, expect: tuple[type, ...]) -> list[tuple[bytes, Any]]:
    """[(item's bytes, item decoded)] of a payload: a `Batch`'s items, or the payload alone.

    Raises ProtocolError naming the bad item when one does not decode as one of ``expect``."""
    if message_kind(payload) != Batch.KIND:
        return [(payload, decode(payload, expect))]
    batch = decode(payload, Batch)
    if not batch.items:
        raise ProtocolError("an empty batch")
    if len(batch.items) > MAX_BATCH_ITEMS:
        raise ProtocolError(f"a batch of {len(batch.items)} messages; at most {MAX_BATCH_ITEMS}")
    out = []
    for i, item in enumerate(batch.items):
        try:
            out.append((item, decode(item, expect)))  # a Batch is not in `expect`: no nesting
        except ProtocolError as exc:
            raise ProtocolError(f"batch item {i + 1} of {len(batch.items)}: {exc}") from exc
    return out
