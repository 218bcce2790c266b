"""The JSON contract, as a script meets it: every `--json` command of the installed `autopower`
prints exactly one JSON object on stdout — on success and on failure — with the keys the table of
docs/reference/json-output.md documents (the table is read from that page, so the two cannot drift).

Commands that need a running team (`status`, `fault …`) are run here against no team (the
failure object); their success objects are parsed by tests/e2e (test_fault_cli, test_up,
test_demo), which check them with `documented_keys` too.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.parallel  # commands that start no team: no live process to share the cores with (tests/conftest.py)

ROOT = Path(__file__).resolve().parents[2]
AUTOPOWER = str(Path(sys.executable).with_name("autopower"))


def documented_keys() -> dict[str, tuple[set[str], set[str], bool]]:
    """The table of docs/reference/json-output.md: command -> (keys always present, keys present
    sometimes, open).

    "Open" (a "…" in the cell) means the documented keys are a subset (the status snapshot)."""
    text = (ROOT / "docs/reference/json-output.md").read_text(encoding="utf-8")
    section = text[text.index("\n| command |"):]
    section = section[:section.index("\n\n")]  # the table ends at the first blank line
    out = {}
    for line in section.splitlines():
        # split on cell bars, not on the escaped "\|" inside a cell
        cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]] if line.startswith("| ") else []
        if len(cells) < 3 or cells[0] == "command":
            continue
        command = cells[0].replace("`", "").replace("\\", "")
        out[command] = (*(set(re.findall(r"`([a-z_0-9]+)`", cell)) for cell in (cells[1], cells[2])), "…" in cells[1])
    return out


def check_keys(command: str, obj: dict) -> None:
    required, optional, open_ended = documented_keys()[command]
    assert isinstance(obj, dict), obj
    assert required <= set(obj), f"{command}: missing {sorted(required - set(obj))}"
    extra = set() if open_ended else set(obj) - required - optional
    assert not extra, f"{command}: undocumented keys {sorted(extra)}; add them to docs/reference/json-output.md"


def run(args: list[str], env: dict, timeout: float = 120.0) -> tuple[subprocess.CompletedProcess, dict]:
    result = subprocess.run([AUTOPOWER, *args], env=env, capture_output=True, text=True, timeout=timeout)
    try:
        obj = json.loads(result.stdout)  # one JSON document, nothing before or after it
    except json.JSONDecodeError as exc:
        raise AssertionError(f"autopower {' '.join(args)}: stdout is not one JSON object ({exc}):\n"
                             f"{result.stdout[:600]}\nstderr: {result.stderr[-600:]}") from None
    assert isinstance(obj, dict)
    return result, obj


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    state = tmp_path_factory.mktemp("state")
    return {**os.environ, "AUTOPOWER_STATE_DIR": str(state), "RERUN_ANALYTICS": "0"}


@pytest.fixture(scope="module")
def recording(tmp_path_factory, env):
    path = tmp_path_factory.mktemp("rec") / "run.rrd"
    result, obj = run(["simulate", "paper-fig7", "--events", "link-cuts", "--record", str(path), "--json"], env)
    assert result.returncode == 0, result.stderr
    check_keys("simulate", obj)
    assert obj["recording"] == str(path)
    return path


SUCCESS = [
    ("analyze", ["analyze", "paper-fig7", "--json"]),
    ("plan", ["plan", "paper-fig7", "--json"]),
    ("plan", ["plan", "paper-fig8", "--json", "--method", "milp", "--no-bound"]),
    ("evaluate", ["evaluate", "paper-fig7", "--place", "Loc-1=laptop", "--media", "laptop-robot=gsm", "--json"]),
    ("evaluate", ["evaluate", "paper-fig7", "--topology", "relay", "--place", "Blob-2=laptop", "--json"]),
    ("simulate", ["simulate", "paper-fig7", "--json"]),
    ("simulate --policy all", ["simulate", "paper-fig7", "--policy", "all", "--json"]),
    ("profile", ["profile", "--runs", "1", "--json"]),
    ("sim", ["sim", "paper-fig7", "--seed", "2", "--mission", "20", "--quiet", "10", "--faults", "2", "--json"]),
]


@pytest.mark.parametrize("command,args", SUCCESS, ids=[" ".join(a) for _, a in SUCCESS])
def test_success_is_one_documented_object(env, command, args):
    result, obj = run(args, env)
    assert result.returncode == 0, result.stderr
    if command == "profile":
        assert set(obj) == {"Blob", "Loc", "TeamMap"} and all("latency_median_s" in v for v in obj.values())
        return
    check_keys(command, obj)
    if command == "analyze":
        for row in obj["rows"]:
            check_keys("analyze row", row)


def test_analyze_rows_and_evaluate_agree_on_a_paper_row(env):
    _, table = run(["analyze", "paper-fig7", "--json", "--only", "paper"], env)
    row = next(r for r in table["rows"] if r["label"] == "paper-row-3")
    places = [a for stage, host in row["allocation"].items() for a in ("--place", f"{stage}={host}")]
    _, ev = run(["evaluate", "paper-fig7", *places, "--topology", row["topology"],
                 "--media", f"laptop-robot={row['laptop_robot_medium']}",
                 "--media", f"robot-robot={row['robot_robot_medium']}", "--json"], env)
    assert ev["lifetime_s"] == row["lifetime_s"] == row["paper_lifetime_s"] == 32976.0
    assert ev["bottleneck"] == row["bottleneck"] and ev["notes"] == []
    assert ev["lifetime_raw_s"] == pytest.approx(min(r["lifetime_raw_s"] for r in ev["robots"].values()))


def test_evaluate_infeasible_names_every_violation(env):
    result, obj = run(["evaluate", "paper-fig7", "--place", "Blob-2=laptop", "--media", "robot-robot=bluetooth",
                       "--media", "laptop-robot=gsm", "--json"], env)
    assert result.returncode == 0  # an infeasible allocation is an answer, not an error
    assert obj["feasible"] is False and obj["lifetime_s"] is None and obj["lifetime_raw_s"] is None
    [v] = obj["violations"]
    assert (v["node"], v["resource"]) == ("r2", "radio:gsm") and v["excess"] > 14
    assert any(note.startswith("Loc-1: not given; runs at its source r1") for note in obj["notes"])


def test_replay_of_a_recording(env, recording):
    for args in (["replay", str(recording), "--json"], ["replay", str(recording), "--json", "--what-if"]):
        result, obj = run(args, env)
        assert result.returncode == 0, result.stderr
        check_keys("replay", obj)


FAILURES = [
    ["analyze", "no-such-scenario", "--json"],
    ["plan", "paper-fig7", "--json", "--without", "r1", "--without", "r2", "--without", "r3"],
    ["plan", "paper-fig7", "--json", "--bogus-option"],
    ["evaluate", "paper-fig7", "--place", "Loc-9=laptop", "--json"],
    ["evaluate", "paper-fig7", "--place", "Loc-1", "--json"],
    ["evaluate", "paper-fig7", "--media", "uplink=gsm", "--json"],
    ["simulate", "paper-fig7", "--events", "no-such-events", "--json"],
    ["replay", "/nonexistent/run.rrd", "--json"],
    ["profile", "--runs", "0", "--json"],
    ["scenarios", "fleet", "0", "--out", "unused.toml", "--json"],
    ["scenarios", "fleet", "3", "--medium", "wifi", "--out", "unused.toml", "--json"],
    ["sim", "no-such-scenario", "--json"],
    ["sim", "--kinds", "no-such-kind", "--json"],
    ["demo", "--mission", "5", "--json"],
    ["up", "no-such-scenario", "--json"],
    ["status", "--json", "--timeout", "1"],
    ["fault", "cut", "r1", "laptop", "--json"],
    ["fault", "list", "--json"],
]


@pytest.mark.parametrize("args", FAILURES, ids=[" ".join(a) for a in FAILURES])
def test_failure_is_one_error_object_and_one_stderr_line(env, args):
    result, obj = run(args, env, timeout=60)
    assert result.returncode == 2, (result.stdout, result.stderr)
    check_keys("any, on failure", obj)
    assert obj["exit_code"] == 2 and obj["error"]
    assert obj["error"] in result.stderr  # the same message, for the human
    assert "Traceback" not in result.stderr


def test_infeasible_pinned_plan_says_what_breaks(env, tmp_path):
    text = (ROOT / "autopower/scenarios/paper-fig7.toml").read_text()
    text = text.replace('laptop_robot_media = ["802.11a", "gsm"]', 'laptop_robot_media = ["gsm"]')
    text = text.replace('name = "Blob-2"\n', 'name = "Blob-2"\npin = "laptop"\n')
    path = tmp_path / "pinned.toml"
    path.write_text(text)
    result, obj = run(["plan", str(path), "--json"], env)
    assert result.returncode == 2
    assert "laptop-robot=gsm" in obj["error"] and "r2 radio:gsm utilisation" in obj["error"]
    assert "any media choice" not in obj["error"]


def test_analyze_shows_an_infeasible_media_pair_with_its_reason(env, tmp_path):
    from tests.unit.test_model_options import TINY

    path = tmp_path / "tiny.toml"
    path.write_text(TINY.format(base_extra="limit_radios = true", up_media='["bluetooth", "802.11a"]',
                                pin='pin = "laptop"', rows=""))
    result, obj = run(["analyze", str(path), "--json", "--only", "optimal"], env)
    assert result.returncode == 0, result.stderr
    rows = {row["media"]["uplink"]: row for row in obj["rows"]}
    assert rows["bluetooth"]["label"] == "infeasible" and rows["bluetooth"]["lifetime_s"] is None
    assert "laptop radio:bluetooth utilisation 120.0%" in rows["bluetooth"]["reason"]
    assert rows["802.11a"]["label"] == "optimal" and rows["802.11a"]["feasible"]
    text = subprocess.run([AUTOPOWER, "analyze", str(path)], env=env, capture_output=True, text=True, timeout=60)
    assert text.returncode == 0
    said = " ".join(text.stdout.split())  # the console wraps long lines
    assert "explicit uplink=bluetooth, cam-amy=802.11a, cam-zed=802.11a: infeasible: no allocation meets" in said


@pytest.mark.parametrize("args", [["fault", "cut", "r1", "laptop", "--team", "nope"],
                                  ["fault", "--team", "nope", "cut", "r1", "laptop"],
                                  ["fault", "list", "--team", "nope"]])
def test_fault_takes_the_team_before_or_after_its_command(env, args):
    """`--team` reads the same wherever a user puts it, and the error names the team that is not
    running without suggesting --connect, which `fault` does not have (it talks to `up` here)."""
    result = subprocess.run([AUTOPOWER, *args], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "no running team 'nope'" in result.stderr and "--connect" not in result.stderr
    assert "No such option" not in result.stderr


def test_fault_refuses_two_different_teams(env):
    result = subprocess.run([AUTOPOWER, "fault", "--team", "a", "heal", "r1", "laptop", "--team", "b"], env=env,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "two teams given: 'a' before the command, 'b' after it" in result.stderr


def test_version_names_autopower_and_the_libraries_it_talks_through(env):
    import tomllib

    expected = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    result = subprocess.run([AUTOPOWER, "--version"], env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and result.stderr == ""
    line, = result.stdout.splitlines()
    assert line.startswith(f"autopower {expected} (eclipse-zenoh ") and "rerun-sdk " in line
    assert "not installed" not in line
