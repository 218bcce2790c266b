"""One strict msgpack codec for every AutoPower message.

Wire form: a msgpack array ``[b"AP", version, kind, {field: value, ...}]``. Decoding checks the
magic, the protocol version, the kind, the exact set of fields and every field's type (nested
structs, tuples, dicts included; numbers finite: NaN and ±inf are refused both ways); anything else raises ProtocolError, which the processes log
and drop. Nothing here trusts the sender.
"""

from __future__ import annotations

import dataclasses
import math
import types
from functools import lru_cache
from typing import Any, Callable, Union, get_args, get_origin, get_type_hints

import msgpack

from autopower.errors import ProtocolError

PROTOCOL_VERSION = 1
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


def _to_wire(value: Any) -> Any:
    # the common cases first, by exact type: every frame of a live team goes through here
    t = type(value)
    if t in _PLAIN:
        return value
    if t is float:
        if not math.isfinite(value):
            raise ValueError(f"non-finite number {value}")
        return value
    names = _field_names(t)
    if names is not None:
        return {name: _to_wire(getattr(value, name)) for name in names}
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"non-finite number {value}")  # the receiver would refuse it: fail at the sender
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _to_wire(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_to_wire(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    return value


def encode(msg: Any) -> bytes:
    """Encode a registered message; raises ProtocolError for anything else."""
    kind = getattr(type(msg), "KIND", None)
    if _MESSAGES.get(kind) is not type(msg):
        raise ProtocolError(f"cannot encode {type(msg).__name__}: not a registered message")
    try:
        return msgpack.packb([MAGIC, PROTOCOL_VERSION, kind, _to_wire(msg)], use_bin_type=True)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ProtocolError(f"cannot encode {kind}: {exc}") from exc


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
                except ProtocolError as exc:
                    errors.append(str(exc))
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
            return tuple(c(v, f"{where}[{i}]") for i, (v, c) in enumerate(zip(value, items)))
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
def _plan(cls: type) -> tuple[tuple[str, ...], frozenset[str], tuple[Callable[[Any, str], Any], ...]]:
    """A class's field names, the names its hints allow, and each field's converter."""
    hints = _hints(cls)
    names = tuple(f.name for f in dataclasses.fields(cls))
    return names, frozenset(hints), tuple(_converter(hints[n]) for n in names)


def _build(cls: type, fields: Any, where: str) -> Any:
    if not isinstance(fields, dict):
        raise _fail(where, f"expected a map of fields, got {type(fields).__name__}")
    names, allowed, converters = _plan(cls)
    if len(fields) != len(names) or any(k not in allowed for k in fields) or any(n not in fields for n in names):
        unknown = [k for k in fields if k not in allowed]
        missing = [n for n in names if n not in fields]
        if unknown or missing:
            detail = []
            if unknown:
                detail.append(f"unknown field(s) {', '.join(map(repr, unknown))}")
            if missing:
                detail.append(f"missing field(s) {', '.join(missing)}")
            raise _fail(where, "; ".join(detail))
    kwargs = {n: c(fields[n], f"{where}.{n}") for n, c in zip(names, converters)}
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise _fail(where, str(exc)) from exc


def looks_like_message(data: bytes) -> bool:
    """Whether ``data`` starts like an encoded message (any version); `decode` still judges the rest."""
    return data[:len(_PREFIX)] == _PREFIX


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
    return _build(cls, fields, kind)


__all__ = ["MAX_MESSAGE_BYTES", "PROTOCOL_VERSION", "decode", "encode", "looks_like_message", "message", "message_kinds", "struct"]
