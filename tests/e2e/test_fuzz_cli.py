"""Fuzzing the command line as users meet it: the installed `autopower` in a subprocess.

Seeded mutations of real command lines (a value swapped for NaN, inf, a huge number, an
empty string, a key-expression wildcard, a malformed endpoint, a very long or non-ASCII
string). Commands that start processes (`up`, `agent`, `basestation`) are only given values
that must be refused, so a mutation never starts a team; the offline commands get anything.
Every run must end within its bound, print no traceback, and report a mistake as one line
with exit 2.
"""

from __future__ import annotations

import random
from concurrent.futures import ThreadPoolExecutor

import pytest

from tests.e2e.test_up import run_cli

pytestmark = pytest.mark.parallel  # commands that start no team: no live process to share the cores with (tests/conftest.py)

BAD = ["nan", "inf", "-inf", "-1", "0", "1e999", "", "a/b", "*", "$x", "tcp/", "tcp/127.0.0.1:99999",
       "udp/[::1", "x" * 3000, "\u00e9\u4e2d\U0001f600", "--", "-5e-324"]
ANY = BAD + ["1", "2.5", "paper-fig7", "r1", "Loc-2", "laptop"]

# (command line with a {} to mutate, whether any value may be tried)
LINES = [
    (["up", "--speed", "{}", "--json", "--duration", "1"], False),
    (["up", "--duration", "{}", "--json"], False),
    (["up", "--energy-scale", "{}", "--json", "--duration", "1"], False),
    (["up", "--lease-ms", "{}", "--json", "--duration", "1"], False),
    (["agent", "--robot", "r1", "--team", "{}", "--duration", "1"], False),
    (["agent", "--robot", "r1", "--connect", "{}", "--duration", "1"], False),
    (["basestation", "--listen", "{}", "--duration", "1"], False),
    (["basestation", "--speed", "{}", "--duration", "1"], False),
    (["check", "{}"], True),
    (["plan", "paper-fig7", "--energy", "r1={}", "--json"], True),
    (["plan", "paper-fig7", "--time-limit", "{}", "--json"], True),
    (["analyze", "{}"], True),
    (["status", "--team", "{}", "--timeout", "1"], True),
    (["status", "--connect", "{}", "--timeout", "1"], True),
]
BOUND_S = 40.0


def _run(case):
    args, env = case
    result = run_cli(args, env, timeout=BOUND_S)  # a hang raises TimeoutExpired: the test fails
    return args, result


def test_mutated_command_lines_fail_with_one_line_and_exit_2(tmp_path):
    from tests.e2e.test_up import env_for

    env = env_for(tmp_path)
    rng = random.Random(12)
    cases = []
    for line, anything in LINES:
        for value in rng.sample(ANY if anything else BAD, 2):
            if not anything and value in ("", "--"):
                value = "nan"  # an empty or option-like value is not a mistake the option sees
            cases.append(([value if a == "{}" else a.replace("{}", value) for a in line], env))
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(_run, cases))
    for args, result in results:
        shown = " ".join(a[:40] for a in args)
        assert "Traceback" not in result.stderr, (shown, result.stderr[-2000:])
        if result.returncode != 0:
            lines = result.stderr.strip().splitlines()
            assert result.returncode == 2, (shown, result.returncode, result.stderr[-500:])
            assert len(lines) == 1 and lines[0].startswith("error: "), (shown, result.stderr[-500:])
    refused = sum(1 for args, r in results if r.returncode == 2)
    assert refused >= len(results) // 2  # the mutations mostly hit the validation they aim at
