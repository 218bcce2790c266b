"""What a user sees first is the answer: the installed `autopower` solves with HiGHS and prints
no solver banner (HiGHS's version and copyright lines) on stdout or stderr, so the text output
starts with the plan and `--json` output is one JSON document."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.parallel  # commands that start no team: no live process to share the cores with (tests/conftest.py)

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([AUTOPOWER, *args], capture_output=True, text=True, timeout=120)


def assert_no_banner(out: subprocess.CompletedProcess) -> None:
    assert out.returncode == 0, out.stderr
    for stream in (out.stdout, out.stderr):
        banner = [line for line in stream.splitlines() if "HiGHS" in line or "Copyright" in line]
        assert not banner, banner


@pytest.mark.parametrize("method", ["auto", "milp"])
def test_plan_prints_the_plan_and_nothing_of_the_solver(method):
    out = run("plan", "paper-fig7", "--method", method)
    assert_no_banner(out)
    assert out.stdout.startswith("paper-fig7 (paper accounting"), out.stdout[:200]
    assert "lifetime" in out.stdout.splitlines()[1]


@pytest.mark.parametrize("method", ["auto", "milp"])
def test_plan_json_is_one_document(method):
    out = run("plan", "paper-fig7", "--method", method, "--json")
    assert_no_banner(out)
    plan = json.loads(out.stdout)  # the whole of stdout, nothing before or after it
    assert plan["lifetime_s"] > 0 and plan["allocation"]


@pytest.mark.parametrize("command", [["analyze", "paper-fig7"], ["simulate", "paper-fig7", "--policy", "rebalance"]])
def test_other_solving_commands_print_no_banner(command):
    assert_no_banner(run(*command))
