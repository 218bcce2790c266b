"""What every real component and its data source look like to the runtime, and their errors.

A *source* lives on the robot that owns an application chain and produces the chain's input
message for step ``seq`` (a camera frame, an odometry + laser message). A *component* turns
one input message into one output message and can run on any computer; whatever it remembers
between steps is its *state*, which must survive ``export_state`` / ``import_state`` so the
component can be migrated mid-run.

Everything here is pure computation: no clocks, no threads, no networking. Outputs are
functions of (constructor arguments, state, payload) only, so runs are reproducible.
"""

from __future__ import annotations

import zlib
from typing import Any, Protocol, runtime_checkable

import msgpack

from autopower.errors import AutoPowerError


class MalformedInputError(AutoPowerError, ValueError):
    """A component was handed a payload it cannot parse (wrong format, size, fields)."""


class ComponentStateError(AutoPowerError, ValueError):
    """A state blob given to ``import_state`` is corrupt or belongs to another component."""


class UnknownComponentTypeError(AutoPowerError, KeyError):
    """No component type of that name is registered."""

    def __str__(self) -> str:
        # KeyError.__str__ would repr() the message and wrap it in quotes.
        return str(self.args[0]) if self.args else ""


@runtime_checkable
class Source(Protocol):
    """Produces the input message of one robot's chain, on that robot, once per period.

    Constructed as ``Cls(robot, seed)``: ``robot`` is the robot that owns the chain (its sensor),
    ``seed`` is the same on every node for that chain. ``produce(seq)`` must be deterministic in
    (robot, seed, seq): a chain's outputs are compared against an offline re-run.
    """

    def produce(self, seq: int) -> bytes:
        """Return the input message for step ``seq`` (``seq >= 0``, increasing by one per period)."""
        ...


@runtime_checkable
class ScoredSource(Source, Protocol):
    """A source that also knows the truth, so a chain's outputs can be scored (optional)."""

    def ground_truth(self, seq: int) -> dict[str, Any]:
        """Return what a perfect component would report for step ``seq`` (plain msgpack-able data)."""
        ...


@runtime_checkable
class Component(Protocol):
    """A placeable piece of robot software: one input message in, one output message out.

    Constructed as ``Cls(robot, seed)`` on whichever node the planner places it (``robot`` is the
    chain's source robot, not the host). ``run`` is called once per input, in sequence order, never
    concurrently; its result must be ``bytes`` no longer than the chain's declared ``message_bytes``
    for that hop. A component that raises, returns anything else, or takes longer than a few of
    its chain's periods is stopped (docs/tutorials/own-component.md: failures are contained).
    """

    def run(self, payload: bytes) -> bytes:
        """Process one input message and return the output message."""
        ...


@runtime_checkable
class StatefulComponent(Component, Protocol):
    """A component that remembers something between runs and can be migrated with it.

    A component without these two methods migrates too, restarted fresh on its new host.
    """

    def export_state(self) -> bytes:
        """Serialise everything the next ``run`` depends on."""
        ...

    def import_state(self, state: bytes) -> None:
        """Replace this instance's state with one produced by ``export_state`` (of another instance).

        Raise (``ComponentStateError``, or anything) if ``state`` is not usable: the migration is
        then abandoned and the component keeps running where it was.
        """
        ...


def pack(obj: Any) -> bytes:
    """msgpack-encode ``obj`` the same way everywhere (bin type for bytes, no single floats)."""
    return msgpack.packb(obj, use_bin_type=True)


def unpack_map(data: bytes, what: str, error: type[ValueError] = MalformedInputError) -> dict[str, Any]:
    """Decode a msgpack map, raising ``error`` with a message naming ``what`` on any failure."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise error(f"{what}: expected bytes, got {type(data).__name__}")
    try:
        obj = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise error(f"{what}: not valid msgpack ({exc.__class__.__name__}: {exc})") from exc
    if not isinstance(obj, dict):
        raise error(f"{what}: expected a msgpack map, got {type(obj).__name__}")
    return obj


def require_fields(obj: dict[str, Any], fields: dict[str, type | tuple[type, ...]], what: str,
                   error: type[ValueError] = MalformedInputError) -> None:
    """Check that ``obj`` has every field in ``fields`` with the given type(s)."""
    for name, kind in fields.items():
        if name not in obj:
            raise error(f"{what}: missing field {name!r} (have {sorted(obj)})")
        value = obj[name]
        # bool is an int subclass; a True where a number belongs is a bug, not a number.
        if isinstance(value, bool) and kind is not bool:
            raise error(f"{what}: field {name!r} must be {_type_names(kind)}, got bool")
        if not isinstance(value, kind):
            raise error(f"{what}: field {name!r} must be {_type_names(kind)}, got {type(value).__name__}")


def _type_names(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(k.__name__ for k in kinds)


def check_seq(seq: int) -> int:
    """Validate a step number: a non-negative int."""
    if isinstance(seq, bool) or not isinstance(seq, int) or seq < 0:
        raise ValueError(f"seq must be a non-negative int, got {seq!r}")
    return seq


def check_seed(seed: int) -> int:
    """Validate a seed: a non-negative int (numpy's SeedSequence refuses negatives)."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}")
    return seed


def robot_key(robot: str) -> int:
    """A stable 32-bit number for a robot name, for seeding (``hash()`` varies per process)."""
    if not isinstance(robot, str) or not robot:
        raise ValueError(f"robot must be a non-empty string, got {robot!r}")
    return zlib.crc32(robot.encode("utf-8"))
