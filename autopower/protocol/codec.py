"""One strict msgpack codec for every AutoPower message.

Wire form: a msgpack array ``[b"AP", version, kind, [value, ...]]``: a message's fields, and a
nested struct's, as an array in the class's declaration order, without their names. Names were
half of every status (a robot's 1,255 B to the base station: 607 B without them) and, on a slow
radio, half of what the control plane costs; the class is known from the kind, and every node runs
the same build (the version says so). Decoding checks the magic, the protocol version, the kind,
the exact number of fields and every field's type (nested structs, tuples, dicts included; numbers
finite: NaN and ±inf are refused both ways); anything else raises ProtocolError, which the
processes log and drop. Nothing here trusts the sender. `wire_data` gives the same values with
their names (an operator's snapshot, JSON; the recorder's look at what its process sends).
"""

from __future__ import annotations

import dataclasses
import math
import types
from functools import lru_cache
from typing import Any, Callable, Union, get_args, get_origin, get_type_hints

import msgpack

from autopower.errors import ProtocolError

PROTOCOL_VERSION = 10  # 2: acknowledgements left the status for `Ack` messages; 3: fields by position;
# 4: statuses as their change from a whole one (`StatusDelta`); 5: a moving stage's unacknowledged
# outputs go with its state (`StateTransfer.outputs`); 6: a `PeerStatus` may name the nodes out of
# its sender's sight instead of those in it (`PeerStatus.unseen`); 7: a robot's plans come on its
# control key, as changes from the plan it holds (`basestation.delivery`), not on the plan key;
# 8: a robot is sent its part of a plan (its own predicted power alone), and a plan's digest hashes
# the plan without its predicted power, then that power (`protocol.plans.plan_digest`); 9: a base
# station's view asks a robot whose whole status it missed for one (`PeerStatus.send_whole`); 10: a
# status says which process of its node sent it and the sources it resumed (`NodeStatus.process`, `resumed`),
# and a packet's purpose may be "backlog" (frames held back while their chain had no route)
MAGIC = b"AP"
# The first bytes of every encoded message (a 4-element array, then the magic): a check cheap
# enough for a transport thread, so that a flood of random bytes is dropped before it is queued.
_PREFIX = b"\x94" + msgpack.packb(MAGIC, use_bin_type=True)
MAX_BIN_BYTES = 64 * 2**20  # the largest byte string a message may carry (a frame's payload)
MAX_MESSAGE_BYTES = MAX_BIN_BYTES + 2**20  # with room for its other fields: nothing larger decodes

_MESSAGES: dict[str, type] = {}  # kind -> class; only these may be top-level
_STRUCTS: set[type] = set()  # nested value types (also frozen dataclasses)


def message(cls: type) -> type:
    """Register a frozen, keyword-only dataclass with a unique ``KIND`` as a wire message."""
    kind = cls.__dict__.get("KIND")
    if not isinstance(kind, str) or not kind:
        raise TypeError(f"{cls.__name__} needs a KIND string")
    if kind in _MESSAGES and _MESSAGES[kind] is not cls:
        raise TypeError(f"two messages share KIND {kind!r}")
    _check_dataclass(cls)
    _MESSAGES[kind] = cls
    return cls


def struct(cls: type) -> type:
    """Register a frozen dataclass used as a field value inside messages."""
    _check_dataclass(cls)
    _STRUCTS.add(cls)
    return cls


def _check_dataclass(cls: type) -> None:
    params = getattr(cls, "__dataclass_params__", None)
    if params is None or not params.frozen:
        raise TypeError(f"{cls.__name__} must be a frozen dataclass")


def message_kinds() -> dict[str, type]:
    return dict(_MESSAGES)


# ---------------------------------------------------------------------------------------------
# encoding
# ---------------------------------------------------------------------------------------------


_PLAIN = frozenset({str, int, bytes, bool, type(None)})  # exact types that go on the wire as they are


@lru_cache(maxsize=None)
def _field_names(cls: type) -> tuple[str, ...] | None:
    """A dataclass's field names, once per class (None: not a dataclass)."""
    return tuple(f.name for f in dataclasses.fields(cls)) if dataclasses.is_dataclass(cls) else None


@lru_cache(maxsize=None)
def _fields_to_wire(cls: type, named: bool) -> Callable[[Any], Any] | None:
    """A dataclass's fields in wire form, compiled once per class (None: not a dataclass): an array
    in declaration order (``named``: a map by field name), what `_wire` does field by field,
    without a call for each field that goes on the wire as it is."""
    names = _field_names(cls)
    if names is None:
        return None
    lines = ["def fields(value):"]
    for i, name in enumerate(names):
        lines.append(f"    _f{i} = value.{name}")
        lines.append(f"    if type(_f{i}) not in _PLAIN: _f{i} = _wire(_f{i}, {named})")
    if named:
        lines.append("    return {" + ", ".join(f"{name!r}: _f{i}" for i, name in enumerate(names)) + "}")
    else:
        lines.append("    return [" + ", ".join(f"_f{i}" for i in range(len(names))) + "]")
    ns: dict[str, Any] = {"_PLAIN": _PLAIN, "_wire": _wire}
    exec("\n".join(lines), ns)  # noqa: S102 - source generated from the class's own field names
    return ns["fields"]


def _wire(value: Any, named: bool = False) -> Any:
    # the common cases first, by exact type: every frame of a live team goes through here
    t = type(value)
    if t in _PLAIN:
        return value
    if t is float:
        if not math.isfinite(value):
            raise ValueError(f"non-finite number {value}")
        return value
    fields = _fields_to_wire(t, named)
    if fields is not None:
        return fields(value)
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"non-finite number {value}")  # the receiver would refuse it: fail at the sender
    if isinstance(value, (tuple, list)):
        return [_wire(v, named) for v in value]
    if isinstance(value, dict):
        return {k: _wire(v, named) for k, v in value.items()}
    return value


def wire_data(value: Any) -> Any:
    """``value`` as the wire carries it, with names: dataclasses as dicts of their fields, tuples as
    lists, the rest as it is (a new container at every level; the leaves are immutable). What an
    operator's snapshot shows of a status, built by the per-class field readers `encode` uses (a
    quarter of `dataclasses.asdict`'s time, which deep-copies every leaf). ValueError for a
    non-finite number, as `encode` refuses it."""
    return _wire(value, named=True)


def encode(msg: Any) -> bytes:
    """Encode a registered message; raises ProtocolError for anything else."""
    return encode_fields(type(msg), wire_fields(msg))


def wire_fields(msg: Any) -> list:
    """A registered message's fields as the wire carries them: a list in declaration order, nested
    structs as lists, tuples as lists (what `encode` packs). ProtocolError for anything else."""
    kind = getattr(type(msg), "KIND", None)
    if _MESSAGES.get(kind) is not type(msg):
        raise ProtocolError(f"cannot encode {type(msg).__name__}: not a registered message")
    try:
        return _wire(msg)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ProtocolError(f"cannot encode {kind}: {exc}") from exc


def encode_fields(cls: type, fields: list) -> bytes:
    """Pack a message of class ``cls`` from its fields in wire form (`wire_fields`); not checked
    against the class: a receiver decodes them as strictly as any message."""
    try:
        return msgpack.packb([MAGIC, PROTOCOL_VERSION, cls.KIND, fields], use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ProtocolError(f"cannot encode {cls.KIND}: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# decoding
# ---------------------------------------------------------------------------------------------


@lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


def _fail(where: str, what: str) -> ProtocolError:
    return ProtocolError(f"{where}: {what}")


def _from_wire(value: Any, hint: Any, where: str) -> Any:
    return _converter(hint)(value, where)


@lru_cache(maxsize=None)
def _converter(hint: Any) -> Callable[[Any, str], Any]:
    """What checks and converts a wire value for ``hint``: worked out once per type hint, not per value."""
    if hint is Any:
        return lambda value, where: value
    origin = get_origin(hint)
    if origin in (Union, types.UnionType):
        options = get_args(hint)
        nullable = type(None) in options
        choices = [_converter(option) for option in options if option is not type(None)]

        def union(value: Any, where: str) -> Any:
            if value is None:
                if nullable:
                    return None
                raise _fail(where, "null is not allowed here")
            errors = []
            for choice in choices:
                try:
                    return choice(value, where)
                except ProtocolError as exc:  # each says where already: said once, below
                    errors.append(str(exc).removeprefix(f"{where}: "))
            raise _fail(where, "; ".join(errors) or f"unexpected {type(value).__name__}")
        return union
    if hint is bool:
        def boolean(value: Any, where: str) -> Any:
            if isinstance(value, bool):
                return value
            raise _fail(where, f"expected bool, got {type(value).__name__}")
        return boolean
    if hint is int:
        def integer(value: Any, where: str) -> Any:
            if isinstance(value, int) and not isinstance(value, bool):
                return value
            raise _fail(where, f"expected int, got {type(value).__name__}")
        return integer
    if hint is float:
        def number(value: Any, where: str) -> Any:
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                try:
                    value = float(value)
                except OverflowError:  # an int too large for a float
                    raise _fail(where, "number out of range") from None
                if not math.isfinite(value):
                    raise _fail(where, f"{value} is not a finite number (NaN and ±inf are refused)")
                return value
            raise _fail(where, f"expected float, got {type(value).__name__}")
        return number
    if hint is str or hint is bytes:
        def exact(value: Any, where: str, kind: type = hint) -> Any:
            if isinstance(value, kind):
                return value
            raise _fail(where, f"expected {kind.__name__}, got {type(value).__name__}")
        return exact
    if origin is tuple:
        args = get_args(hint)
        if len(args) == 2 and args[1] is Ellipsis:
            item = _converter(args[0])

            def variadic(value: Any, where: str) -> Any:
                if not isinstance(value, (list, tuple)):
                    raise _fail(where, f"expected a list, got {type(value).__name__}")
                return tuple(item(v, f"{where}[{i}]") for i, v in enumerate(value))
            return variadic
        items = [_converter(a) for a in args]

        def fixed(value: Any, where: str) -> Any:
            if not isinstance(value, (list, tuple)):
                raise _fail(where, f"expected a list, got {type(value).__name__}")
            if len(items) != len(value):
                raise _fail(where, f"expected {len(items)} items, got {len(value)}")
            return tuple(c(v, f"{where}[{i}]") for i, (v, c) in enumerate(zip(value, items, strict=True)))
        return fixed
    if origin is dict:
        key_t, val_t = get_args(hint)
        key_c, val_c = _converter(key_t), _converter(val_t)

        def mapping(value: Any, where: str) -> Any:
            if not isinstance(value, dict):
                raise _fail(where, f"expected a map, got {type(value).__name__}")
            return {key_c(k, f"{where}.<key>"): val_c(v, f"{where}[{k!r}]") for k, v in value.items()}
        return mapping

    def registered(value: Any, where: str) -> Any:  # looked up when used: classes register at import
        if isinstance(hint, type) and (hint in _STRUCTS or hint in _MESSAGES.values()):
            return _build(hint, value, where)
        raise _fail(where, f"unsupported field type {hint!r}")  # a bug in a message definition
    return registered


@lru_cache(maxsize=None)
def _plan(cls: type) -> tuple[tuple[str, ...], tuple[Callable[[Any, str], Any], ...]]:
    """A class's field names and each field's converter."""
    hints = _hints(cls)
    names = tuple(f.name for f in dataclasses.fields(cls))
    return names, tuple(_converter(hints[n]) for n in names)


def _build(cls: type, fields: Any, where: str) -> Any:
    names, converters = _plan(cls)
    if not isinstance(fields, list):
        raise _fail(where, f"expected the {len(names)} fields of {cls.__name__} as a list, got {type(fields).__name__}")
    if len(fields) != len(names):
        said = f"{len(names)} fields ({', '.join(names)})"
        raise _fail(where, f"expected {said}, got {len(fields)}: a node of another AutoPower build? "
                           "Run the same version on every node")
    kwargs = {n: c(v, f"{where}.{n}") for n, c, v in zip(names, converters, fields, strict=True)}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise _fail(where, str(exc)) from exc


# ---- the fast path: the same checks, compiled once per class ------------------------------------
#
# `_build` above names the place of every value it checks (an f-string per field and item, built
# whether or not anything is wrong) and calls a converter per value: on a live team that was most
# of what a status or a frame costs to decode. `_fast_builder(cls)` compiles one function per
# class that checks the same things inline and builds the same object; on anything it does not
# accept outright it gives up (`_Slow`) and the message is decoded again by `_build`, which accepts
# or refuses it and says where. So the fast path may refuse more, never accept more: every value
# it lets through has the exact type and range the slow path would have produced.


class _Slow(Exception):
    """The fast path does not vouch for this value: decode it again the slow way."""


_PRIMITIVE_CHECK = {bool: "bool", int: "int", str: "str", bytes: "bytes"}


class _Compiler:
    """Python source of a class's fast builder (one function; nested structs call theirs)."""

    def __init__(self, namespace: dict[str, Any]):
        self.ns = namespace
        self.lines: list[str] = []
        self.n = 0

    def var(self) -> str:
        self.n += 1
        return f"_v{self.n}"

    def emit(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)

    def value(self, hint: Any, src: str, indent: int) -> str:
        """Lines that check ``src`` against ``hint``; returns the expression of its converted value."""
        if hint is Any:
            return src
        if hint in _PRIMITIVE_CHECK:
            self.emit(indent, f"if type({src}) is not {_PRIMITIVE_CHECK[hint]}: raise _Slow")
            return src
        if hint is float:
            out = self.var()
            self.emit(indent, f"if type({src}) is float: {out} = {src}")
            self.emit(indent, f"elif type({src}) is int and -_BIG < {src} < _BIG: {out} = float({src})")
            self.emit(indent, "else: raise _Slow")
            self.emit(indent, f"if {out} - {out} != 0.0: raise _Slow")  # NaN or an infinity
            return out
        origin, args = get_origin(hint), get_args(hint)
        if origin in (Union, types.UnionType) and len(args) == 2 and type(None) in args:
            (inner,) = [a for a in args if a is not type(None)]
            out = self.var()
            self.emit(indent, f"if {src} is None: {out} = None")
            self.emit(indent, "else:")
            self.emit(indent + 1, f"{out} = {self.value(inner, src, indent + 1)}")
            return out
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            out, item = self.var(), self.var()
            self.emit(indent, f"if type({src}) is not list: raise _Slow")
            self.emit(indent, f"{out} = []")
            self.emit(indent, f"for {item} in {src}:")
            self.emit(indent + 1, f"{out}.append({self.value(args[0], item, indent + 1)})")
            return f"tuple({out})"
        if origin is dict:
            out, key, val = self.var(), self.var(), self.var()
            self.emit(indent, f"if type({src}) is not dict: raise _Slow")
            self.emit(indent, f"{out} = {{}}")
            self.emit(indent, f"for {key}, {val} in {src}.items():")
            k = self.value(args[0], key, indent + 1)
            v = self.value(args[1], val, indent + 1)
            self.emit(indent + 1, f"{out}[{k}] = {v}")
            return out
        if isinstance(hint, type) and (hint in _STRUCTS or hint in _MESSAGES.values()):
            name = f"_build_{hint.__name__}"
            self.ns[name] = _lazy_builder(hint)  # compiled at its first use (a class may refer to itself)
            return f"{name}({src})"
        # anything else (a union of several types, a fixed tuple): the slow converter, unnamed
        name = f"_convert{self.var()}"
        self.ns[name] = _converter(hint)
        out = self.var()
        self.emit(indent, f"try: {out} = {name}({src}, '')")
        self.emit(indent, "except ProtocolError: raise _Slow from None")
        return out


def _lazy_builder(cls: type) -> Callable[[Any], Any]:
    built: list[Callable[[Any], Any]] = []

    def build(fields: Any) -> Any:
        if not built:
            built.append(_fast_builder(cls))
        return built[0](fields)
    return build


@lru_cache(maxsize=None)
def _fast_builder(cls: type) -> Callable[[Any], Any]:
    names, _ = _plan(cls)
    hints = _hints(cls)
    ns: dict[str, Any] = {"_Slow": _Slow, "ProtocolError": ProtocolError, "_cls": cls, "_BIG": 2.0**1023,
                          "_new": object.__new__}
    c = _Compiler(ns)
    c.emit(0, "def build(fields):")
    c.emit(1, f"if type(fields) is not list or len(fields) != {len(names)}: raise _Slow")
    if names:
        c.emit(1, ", ".join(f"_f{i}" for i in range(len(names))) + ", = fields")
    values = [c.value(hints[name], f"_f{i}", 1) for i, name in enumerate(names)]
    # what the frozen dataclass's __init__ does (every field is on the wire: no defaults to fill),
    # without its object.__setattr__ per field; its __post_init__ still judges the values
    c.emit(1, "obj = _new(_cls)")
    c.emit(1, "obj.__dict__.update(" + ", ".join(f"{n}={v}" for n, v in zip(names, values, strict=True)) + ")")
    if hasattr(cls, "__post_init__"):
        c.emit(1, "try: obj.__post_init__()")
        c.emit(1, "except (TypeError, ValueError): raise _Slow from None")
    c.emit(1, "return obj")
    exec("\n".join(c.lines), ns)  # noqa: S102 - source generated above from the class's own type hints
    return ns["build"]


_FAST: dict[type, Callable[[Any], Any]] = {}  # message class -> its compiled builder


def _decode_fields(cls: type, fields: Any, kind: str) -> Any:
    build = _FAST.get(cls)
    if build is None:
        build = _FAST[cls] = _fast_builder(cls)
    try:
        return build(fields)
    except _Slow:
        return _build(cls, fields, kind)  # accepts it after all, or says what is wrong and where


def decode_fields(cls: type, fields: Any) -> Any:
    """A registered message of class ``cls`` built from its fields in wire form (as `decode` reads
    them off the wire, with the same checks); ProtocolError for anything it would refuse."""
    if _MESSAGES.get(getattr(cls, "KIND", None)) is not cls:
        raise ProtocolError(f"cannot decode {cls.__name__}: not a registered message")
    return _decode_fields(cls, fields, cls.KIND)


def looks_like_message(data: bytes) -> bool:
    """Whether ``data`` starts like an encoded message (any version); `decode` still judges the rest."""
    return data[:len(_PREFIX)] == _PREFIX


def message_kind(data: bytes) -> str | None:
    """The kind an encoded message says it is (``"frame"``, ``"status"``, ...), read from its header
    alone (for counting traffic); None when it does not start like a message. Not a validation."""
    if not looks_like_message(data):
        return None
    header = msgpack.Unpacker(raw=False)
    header.feed(bytes(data[len(_PREFIX):len(_PREFIX) + 64]))  # the version and the kind: a few bytes
    try:
        header.unpack()
        kind = header.unpack()
    except Exception:  # msgpack raises many unrelated types on garbage
        return None
    return kind if isinstance(kind, str) else None


def decode(data: bytes | bytearray | memoryview, expect: type | tuple[type, ...] | None = None) -> Any:
    """Decode one message, strictly. ``expect`` limits which message classes are acceptable here."""
    try:
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=False, max_bin_len=MAX_BIN_BYTES)
    except Exception as exc:  # msgpack raises many unrelated types on garbage
        raise ProtocolError(f"not a msgpack message ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(obj, list) or len(obj) != 4:
        raise ProtocolError(f"not an AutoPower message (expected [magic, version, kind, fields], got {type(obj).__name__})")
    magic, version, kind, fields = obj
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r}; not an AutoPower message")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {version!r}; this build speaks {PROTOCOL_VERSION}. "
                            "Run the same AutoPower version on every node")
    if not isinstance(kind, str):
        raise ProtocolError(f"message kind must be a string, got {type(kind).__name__}")
    cls = _MESSAGES.get(kind)
    if cls is None:
        raise ProtocolError(f"unknown message kind {kind!r}")
    if expect is not None:
        allowed = expect if isinstance(expect, tuple) else (expect,)
        if cls not in allowed:
            raise ProtocolError(f"message kind {kind!r} is not accepted here "
                                f"(expected {', '.join(c.KIND for c in allowed)})")
    return _decode_fields(cls, fields, kind)


__all__ = ["MAX_MESSAGE_BYTES", "PROTOCOL_VERSION", "decode", "decode_fields", "encode", "encode_fields",
           "looks_like_message", "message", "message_kind", "wire_data", "wire_fields", "message_kinds", "struct"]
