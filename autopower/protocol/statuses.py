"""Statuses on the wire: whole (`NodeStatus`, a keyframe) or as their change from the sender's last
whole one (`StatusDelta`).

Most of a status repeats from one to the next (hosted stages, links, generations, sinks' runs,
counters, the names of the energy parts); its clock, battery and meters do not. A status goes as
its change from the last keyframe its sender sent, cumulative, not chained: a receiver that
missed a delta loses nothing, the next one carries all that changed since the keyframe.

Rules (`StatusEncoder`, one per sending process; `StatusAssembler`, one per receiving process):
- a keyframe goes instead of a delta: the process's first status (a restarted process starts
  anew); a status whose change would exceed `KEY_FRACTION` of the keyframe; `KEY_EVERY_S` after the
  last keyframe (a receiver that missed one, or started listening, has the sender's whole status
  within that bound); a status whose links differ from the status before (a node came into
  sight or left it: one that was cut off missed what was sent meanwhile) or whose mission differs
  from the keyframe's (a base station taking the team over asks for it, `NodeRuntime._mission_wanted`);
  and the next status after `StatusEncoder.refresh` (a base station began listening);
- a keyframe is named by its ``t_unix``: a sender's keyframes go out at increasing wall times (a
  status due as a keyframe at the time of the last one goes as a delta);
- a receiver holds, per sender, its keyframe with the latest ``t_unix``, and applies a delta only
  to the keyframe it names (``key_t``). Any other delta is ignored and counted (`unapplied`): an
  older delta arriving after a newer keyframe names the older one and never rolls a view back. A
  receiver without the keyframe asks for one (`take_wanted`: a base station's view to that robot
  says ``send_whole``) instead of waiting up to `KEY_EVERY_S` for it: a keyframe lost on a lossy
  link kept a base station's view of a robot (and of whom it sees) stale for 10 s, long enough to
  take a robot nobody reached for one reached through a relay. A delta still shows that its sender
  is there: callers count it as heard before they assemble it;
- a delta is turned into the whole status's wire form and decoded as strictly as a status sent
  whole; one that changes the sender's name or clock through ``changes``, names a field or a
  key position the keyframe does not have, or has a map field's change in another shape raises
  `ProtocolError`, which callers count and drop;
- a map built from a delta has the keyframe's keys in the keyframe's order, new keys after: equal
  as a map to what the sender built, not always in its order.
"""

from __future__ import annotations

import dataclasses
from typing import Any, get_args, get_origin, get_type_hints

from autopower.errors import ProtocolError
from autopower.protocol.codec import decode_fields, encode, encode_fields, message_kind, wire_fields
from autopower.protocol.messages import NodeStatus, StatusDelta

KEY_EVERY_S = 10.0  # wall seconds between keyframes at the latest: 5 heartbeats at rest, 20 periods running
KEY_FRACTION = 0.5  # a change larger than this share of the keyframe goes whole
MAX_SENDERS = 4096  # senders whose keyframe a receiver holds (the earliest held goes first)

_NAMES = tuple(f.name for f in dataclasses.fields(NodeStatus))
_NODE, _T_UNIX, _MISSION = _NAMES.index("node"), _NAMES.index("t_unix"), _NAMES.index("mission")
_FIXED = frozenset({_NODE, _T_UNIX})  # carried by the delta itself, never in its changes
_HINTS = get_type_hints(NodeStatus)
_MAPS = frozenset(i for i, name in enumerate(_NAMES) if get_origin(_HINTS[name]) is dict)
# a key in a map's change is a position when it is an int: every map of a status is keyed by name
assert all(get_args(_HINTS[_NAMES[i]])[0] is str for i in _MAPS)

_MISSING = object()


def replaces_queued(payload: bytes) -> bool:
    """Whether a status still queued for the receiver's loop may be replaced by the newer one
    ``payload`` is: a delta may (it carries all since its keyframe, and an older delta is no
    base for anything), a keyframe may not (the deltas after it need it). Read from the header."""
    return message_kind(payload) == StatusDelta.KIND


def _same(a: Any, b: Any) -> bool:
    """Equal, and of one type (True == 1 and 1 == 1.0 in Python; not on the wire)."""
    return type(a) is type(b) and a == b


class StatusEncoder:
    """A sending process's statuses as the bytes to publish: each a keyframe or a delta from the last one."""

    def __init__(self, *, key_every_s: float = KEY_EVERY_S, key_fraction: float = KEY_FRACTION):
        self.key_every_s = key_every_s
        self.key_fraction = key_fraction
        self._key: list | None = None  # the keyframe's fields in wire form
        self._key_t = 0.0
        self._key_bytes = 0
        self._positions: dict[int, dict[str, int]] = {}  # map field -> its keys' positions in the keyframe
        self._last_links: dict[str, bool] | None = None
        self._asked = False
        self.keyframes = 0
        self.deltas = 0

    def refresh(self) -> None:
        """The next status goes whole (a receiver began listening)."""
        self._asked = True

    def encode(self, status: NodeStatus) -> bytes:
        fields = wire_fields(status)
        links_moved = self._last_links is not None and status.links != self._last_links
        self._last_links = status.links
        key = self._key
        if key is None or key[_NODE] != fields[_NODE]:
            return self._keyframe(fields)
        may_key = status.t_unix > self._key_t  # one keyframe per t_unix: it names the keyframe
        if may_key and (self._asked or links_moved or status.t_unix - self._key_t >= self.key_every_s
                        or not _same(fields[_MISSION], key[_MISSION])):
            return self._keyframe(fields)
        delta = encode(StatusDelta(node=status.node, t_unix=status.t_unix, key_t=self._key_t,
                                   changes=self._changes(key, fields)))
        # against the keyframe's size (a status's size moves little between keyframes): no second encoding
        if may_key and len(delta) > self.key_fraction * self._key_bytes:
            return self._keyframe(fields)
        self.deltas += 1
        return delta

    def _keyframe(self, fields: list) -> bytes:
        whole = encode_fields(NodeStatus, fields)
        self._key, self._key_t, self._key_bytes, self._asked = fields, fields[_T_UNIX], len(whole), False
        self._positions = {i: {k: p for p, k in enumerate(fields[i])} for i in _MAPS}
        self.keyframes += 1
        return whole

    def _changes(self, key: list, fields: list) -> dict[int, Any]:
        out: dict[int, Any] = {}
        for i, (old, new) in enumerate(zip(key, fields, strict=True)):
            if i in _FIXED:
                continue
            if i in _MAPS:
                positions = self._positions[i]
                changed = {positions.get(k, k): v for k, v in new.items() if not _same(old.get(k, _MISSING), v)}
                gone = [positions[k] for k in old if k not in new]
                if changed or gone:
                    out[i] = [changed, gone]
            elif not _same(old, new):
                out[i] = new
        return out


@dataclasses.dataclass(frozen=True)
class _Keyframe:
    t_unix: float
    fields: list  # in wire form
    keys: dict[int, list[str]]  # map field -> its keys in order


class StatusAssembler:
    """A receiving process's view of each sender's statuses: whole ones from keyframes and deltas."""

    def __init__(self, *, max_senders: int = MAX_SENDERS):
        self._held: dict[str, _Keyframe] = {}
        self._max_senders = max_senders
        self.unapplied = 0  # deltas whose keyframe was not held (missed, or superseded by a newer one)
        self._wanted: set[str] = set()  # senders whose keyframe this receiver missed (`take_wanted`)

    def whole(self, msg: NodeStatus | StatusDelta) -> NodeStatus | None:
        """The whole status ``msg`` is or makes; None for a delta this receiver cannot apply.
        Raises `ProtocolError` for a delta that does not make a valid status."""
        if isinstance(msg, NodeStatus):
            held = self._held.get(msg.node)
            if held is None or msg.t_unix > held.t_unix:
                self._hold(msg)
            return msg
        held = self._held.get(msg.node)
        if held is None or held.t_unix != msg.key_t:
            self.unapplied += 1
            if held is None or held.t_unix < msg.key_t:  # missed (not an older delta overtaken)
                self._wanted.add(msg.node)
            return None
        return decode_fields(NodeStatus, self._applied(held, msg))

    def take_wanted(self) -> set[str]:
        """The senders whose whole status this receiver missed since last asked (a delta named a
        keyframe it does not hold, newer than the one it holds): to be asked for one at once."""
        wanted, self._wanted = self._wanted, set()
        return wanted

    def holds(self, node: str) -> float | None:
        """The ``t_unix`` of the keyframe held for ``node`` (None: none)."""
        held = self._held.get(node)
        return None if held is None else held.t_unix

    def _hold(self, status: NodeStatus) -> None:
        fields = wire_fields(status)
        self._held.pop(status.node, None)
        self._held[status.node] = _Keyframe(t_unix=status.t_unix, fields=fields,
                                            keys={i: list(fields[i]) for i in _MAPS})
        while len(self._held) > self._max_senders:
            del self._held[next(iter(self._held))]

    @staticmethod
    def _applied(held: _Keyframe, delta: StatusDelta) -> list:
        out = list(held.fields)
        for i, value in delta.changes.items():
            if i in _FIXED or not 0 <= i < len(out):
                raise ProtocolError(f"status-delta from {delta.node}: no field {i} to change")
            out[i] = _applied_map(held.fields[i], held.keys[i], value, _NAMES[i]) if i in _MAPS else value
        out[_T_UNIX] = delta.t_unix
        return out


def _applied_map(old: dict, keys: list[str], change: Any, name: str) -> dict:
    if type(change) is not list or len(change) != 2 or type(change[0]) is not dict or type(change[1]) is not list:
        raise ProtocolError(f"status-delta.{name}: expected [entries new or changed, keys gone]")
    changed, gone = change
    out = dict(old)
    for position in gone:
        out.pop(_key_at(keys, position, name), None)
    for k, v in changed.items():
        out[_key_at(keys, k, name) if type(k) is int else k] = v  # a name: the status's decoding checks it
    return out


def _key_at(keys: list[str], position: Any, name: str) -> str:
    if type(position) is not int or not 0 <= position < len(keys):
        raise ProtocolError(f"status-delta.{name}: no key at position {position!r} in the keyframe")
    return keys[position]


__all__ = ["KEY_EVERY_S", "KEY_FRACTION", "StatusAssembler", "StatusEncoder", "replaces_queued"]
