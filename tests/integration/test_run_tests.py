"""`./run tests` as CI and a developer run it: two passes that together are the whole suite."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.parallel  # collects and parses options only: no test runs, no team starts


def run_tests(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(ROOT / "run"), "tests", *args], cwd=ROOT, capture_output=True, text=True, timeout=240)


def test_the_two_passes_together_collect_every_test_once():
    whole = subprocess.run([str(ROOT / ".venv" / "bin" / "python"), "-m", "pytest", "--co", "-q", "-p", "no:cacheprovider"],
                           cwd=ROOT, capture_output=True, text=True, timeout=240)
    total = int(re.search(r"(\d+) tests collected", whole.stdout).group(1))
    passes = run_tests("--co", "-q", "-p", "no:cacheprovider")
    assert passes.returncode == 0, passes.stderr[-600:]
    counts = [(int(n), int(of)) for n, of in re.findall(r"(\d+)/(\d+) tests collected", passes.stdout)]
    assert len(counts) == 2 and all(of == total for _, of in counts), passes.stdout[-600:]
    assert counts[0][0] > 0 and counts[1][0] > 0 and counts[0][0] + counts[1][0] == total


def test_a_wrong_option_is_one_error_and_no_second_pass():
    result = run_tests("--no-such-option")
    assert result.returncode == 4
    assert (result.stdout + result.stderr).count("unrecognized arguments: --no-such-option") == 1
