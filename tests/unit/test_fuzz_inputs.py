"""Fuzzing the doors that take input from files and the network: no traceback, no hang.

Scenario files: seeded mutations of paper-fig7 (values swapped for NaN, inf, huge or wrong
types; lines dropped, duplicated or cut; bytes flipped; nesting piled up) must load or give one
ScenarioError line, each within a bound. Messages: random bytes, random msgpack structures
shaped like a message, and bit flips of real messages must decode or give a ProtocolError.
The CLI's own door is fuzzed as a subprocess in tests/e2e/test_fuzz_cli.py.
"""

from __future__ import annotations

import random
import re
import time
from importlib import resources

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.errors import ProtocolError, ScenarioError
from autopower.model.loading import parse_scenario
from autopower.protocol import PROTOCOL_VERSION, decode, encode, message_kinds
from tests.unit.test_protocol import SAMPLES

PAPER = (resources.files("autopower.scenarios") / "paper-fig7.toml").read_text()
ODD_VALUES = ["nan", "inf", "-inf", "-0.0", "0", "-1", "1e308", "1e-320", "9" * 40, "-" + "9" * 400, '""',
              '"x"', "true", "[]", "{}", "[1, [2, [3]]]", "1979-05-27T07:32:00Z", '"\u00e9\u4e2d\U0001f600"']
LOAD_BOUND_S = 2.0


def mutate(text: str, rng: random.Random) -> str:
    lines = text.splitlines()
    kind = rng.randrange(8)
    i = rng.randrange(len(lines))
    if kind <= 2:  # a value swapped for something odd
        values = [j for j, l in enumerate(lines) if re.match(r"^\s*[\w\"]+\s*=", l)]
        j = rng.choice(values)
        key = lines[j].split("=", 1)[0]
        lines[j] = f"{key}= {rng.choice(ODD_VALUES)}"
    elif kind == 3:
        del lines[i]
    elif kind == 4:
        lines.insert(i, lines[rng.randrange(len(lines))])
    elif kind == 5:
        return "\n".join(lines)[: rng.randrange(len(text))]
    elif kind == 6:
        raw = bytearray("\n".join(lines).encode())
        for _ in range(rng.randint(1, 4)):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
        return raw.decode("utf-8", errors="replace")
    else:
        depth = rng.choice([50, 500, 5000])
        lines.insert(i, "deep = " + "[" * depth + "]" * depth)
    return "\n".join(lines)


def test_mutated_scenarios_load_or_fail_with_one_line():
    rng = random.Random(12)
    outcomes = {"ok": 0, "refused": 0}
    for n in range(400):
        text = mutate(PAPER, rng)
        started = time.monotonic()
        try:
            parse_scenario(text, "fuzz.toml")
            outcomes["ok"] += 1
        except ScenarioError as exc:
            message = str(exc)
            assert message.startswith("fuzz.toml") and "\n" not in message and len(message) < 600, (n, message)
            outcomes["refused"] += 1
        # any other exception fails the test with its traceback: that is the bug to fix
        assert time.monotonic() - started < LOAD_BOUND_S, (n, text[:300])
    assert outcomes["ok"] > 20 and outcomes["refused"] > 200  # the mutations reach both outcomes


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=512))
def test_random_bytes_never_raise_anything_but_protocol_error(data):
    try:
        decode(data)
    except ProtocolError:
        pass


_scalars = st.one_of(st.none(), st.booleans(), st.integers(min_value=-2**63, max_value=2**64 - 1),
                     st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20), st.binary(max_size=20))
_values = st.recursive(_scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                         st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                       max_leaves=20)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(sorted(message_kinds())), data=st.data())
def test_message_shaped_garbage_decodes_strictly(kind, data):
    """The right number of fields with random values: decoded only if every value has its declared type."""
    cls = message_kinds()[kind]
    names = list(cls.__dataclass_fields__)
    fields = [data.draw(_values, label=name) for name in names]
    raw = msgpack.packb([b"AP", PROTOCOL_VERSION, kind, fields], use_bin_type=True)
    try:
        msg = decode(raw)
    except ProtocolError:
        return
    assert decode(encode(msg)) == msg  # whatever is accepted is a well-formed message


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(index=st.integers(min_value=0, max_value=len(SAMPLES) - 1), flips=st.lists(
    st.tuples(st.integers(min_value=0), st.integers(min_value=0, max_value=255)), min_size=1, max_size=6))
def test_bit_flipped_messages_decode_or_are_refused(index, flips):
    raw = bytearray(encode(SAMPLES[index]))
    for position, byte in flips:
        raw[position % len(raw)] = byte
    try:
        decode(bytes(raw))
    except ProtocolError:
        pass


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_no_message_with_a_float_field_accepts_non_finite_numbers(value):
    checked = 0
    for kind, cls in message_kinds().items():
        for sample in SAMPLES:
            if type(sample) is not cls:
                continue
            fields = msgpack.unpackb(encode(sample), raw=False, strict_map_key=False)[3]  # as `decode` reads it
            for at, current in enumerate(fields):
                if isinstance(current, float):
                    changed = [*fields[:at], value, *fields[at + 1:]]
                    raw = msgpack.packb([b"AP", PROTOCOL_VERSION, kind, changed], use_bin_type=True)
                    with pytest.raises(ProtocolError, match="finite"):
                        decode(raw)
                    checked += 1
    assert checked >= 5
