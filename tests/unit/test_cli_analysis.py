"""`autopower analyze|plan|check` as a user runs them (the installed console script)."""

import json
import subprocess
import sys
from importlib import resources

import pytest
from click.testing import CliRunner

from autopower.cli.main import cli
from autopower.model.loading import apply_latency_profile

PAPER = (resources.files('autopower.scenarios') / 'paper-fig7.toml').read_text()


def run(*args):
    # the real entry point, as a user would call it: errors must be one line, no traceback
    return subprocess.run([sys.executable, "-m", "autopower.cli.main", *args], capture_output=True, text=True, timeout=120)


def test_analyze_json_schema_and_fig7_rows():
    out = CliRunner().invoke(cli, ["analyze", "paper-fig7", "--json"])
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    assert data["scenario"] == "paper-fig7" and data["accounting"] == "paper"
    rows = data["rows"]
    for row in rows:
        assert row["topology"] in ("fully-connected", "relay")
        assert row["laptop_robot_medium"] in ("802.11a", "bluetooth", "gsm")
        assert row["robot_robot_medium"] in ("802.11a", "bluetooth", "gsm")
        assert set(row["allocation"]) == {"Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3"}
        assert isinstance(row["feasible"], bool)
        assert (row["lifetime_s"] is None) == (not row["feasible"])
    paper = [r for r in rows if r["label"].startswith("paper-row-")]
    assert len(paper) == 16
    assert all(r["lifetime_s"] == r["paper_lifetime_s"] for r in paper)
    optimal = [r for r in rows if r["label"] == "optimal"]
    assert len(optimal) == 8  # 2 topologies x 4 media pairs
    best = max(optimal, key=lambda r: r["lifetime_s"] or 0)
    assert best["lifetime_s"] == 45715.2 and best["bottleneck"] == "r2"
    assert data["normalized_by_s"] == 29121.6


def test_analyze_energy_override_and_physical_mode():
    out = CliRunner().invoke(cli, ["analyze", "paper-fig7", "--energy", "r1=32000", "--accounting", "physical", "--json"])
    data = json.loads(out.output)
    assert data["accounting"] == "physical" and data["energies_j"]["r1"] == 32000
    paper_rows = {r["label"]: r for r in data["rows"] if r["label"].startswith("paper-row-")}
    assert paper_rows["paper-row-1"]["lifetime_s"] != 45715.2  # physical mode changes the numbers


def test_plan_json_has_reasons_and_bound():
    out = CliRunner().invoke(cli, ["plan", "paper-fig8", "--json"])
    data = json.loads(out.output)
    assert data["lifetime_s"] == 23860.8
    assert set(data["reasons"]) == {"Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3"}
    assert data["time_sharing_bound"]["lifetime_s"] >= data["lifetime_raw_s"] - 1e-6


def test_plan_table_prints():
    out = CliRunner().invoke(cli, ["plan", "paper-fig7"])
    assert out.exit_code == 0 and "45715.2 s" in out.output and "time-sharing bound" in out.output


@pytest.mark.parametrize("args, message", [
    (["analyze", "no-such-scenario"], "neither a scenario file nor a built-in"),
    (["analyze", "--energy", "r9=100"], "unknown robot 'r9'"),
    (["analyze", "--energy", "r1"], "expected ROBOT=JOULES"),
    (["plan", "--disable", "Blob-9"], "unknown chain 'Blob-9'"),
])
def test_errors_are_one_line_without_traceback(args, message):
    proc = run(*args)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.startswith("error: ")


def test_check_reports_file_and_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[scenario]\nname = 'x'\n[platforms.p]\nidle_w = 1\nbusy_w = 2\nfoo = 3\n")
    proc = run("check", str(bad))
    assert proc.returncode == 2
    assert f"{bad}" in proc.stderr
    assert "missing required keys 'radios', 'robots', 'basestation', 'network', 'components', 'chains'" in proc.stderr
    good_but_typo = PAPER.replace("busy_w = 2.27", "busy_w = 2.27\nfoo = 3")
    bad.write_text(good_but_typo)
    proc = run("check", str(bad))
    assert proc.returncode == 2 and "platforms.sitsang.foo: unknown key" in proc.stderr
    line = int(proc.stderr.split(f"{bad}:")[1].split(":")[0])
    assert good_but_typo.splitlines()[line - 1] == "foo = 3"
    bad.write_text(PAPER)
    ok = run("check", str(bad))
    assert ok.returncode == 0 and "5 chains" in ok.stdout


def test_profile_writes_a_file_the_planner_uses(tmp_path):
    out_file = tmp_path / "prof.toml"
    res = CliRunner().invoke(cli, ["profile", "--runs", "3", "--out", str(out_file)])
    assert res.exit_code == 0, res.output
    text = out_file.read_text()
    assert "[latency_s]" in text and "Blob = " in text and "Loc = " in text
    # A platform as fast as this machine makes local computation cheap: the plan changes.
    from autopower.model.loading import load_scenario
    s = apply_latency_profile(load_scenario("paper-fig7"), out_file, "sitsang")
    assert s.components["Loc"].latency_s["sitsang"] < 0.1
    res = CliRunner().invoke(cli, ["plan", "paper-fig7", "--latency-profile", str(out_file), "--as-platform", "sitsang", "--json", "--no-bound"])
    assert json.loads(res.output)["lifetime_s"] > 45715.2


def test_profile_prints_the_live_limit_of_the_default_mission():
    """The speed-up at which paper-fig7's components alone would take every core here, as measured."""
    import os
    import re

    from autopower.chains.profile import live_limit
    from autopower.model.loading import load_scenario

    res = CliRunner().invoke(cli, ["profile", "--runs", "3"])
    assert res.exit_code == 0, res.output
    found = re.search(r"live limit of paper-fig7 here: its components need ([0-9.]+) ms of CPU per virtual second "
                      r"-> x([0-9]+) on ([0-9]+) cores", " ".join(res.output.split()))
    assert found, res.output
    need_ms, limit, cores = float(found[1]), int(found[2]), int(found[3])
    assert cores == (os.cpu_count() or 1)
    assert abs(limit - cores / (need_ms / 1e3)) <= 0.5 + limit * 0.01  # the line is self-consistent
    # and the need is the chains' runs per virtual second times the medians: Blob at 0.1 s, Loc at 1 s
    profile = {"Blob": {"latency_median_s": 0.1}, "Loc": {"latency_median_s": 1.0}}
    need, limit = live_limit(load_scenario("paper-fig7"), profile, 2)
    assert need == pytest.approx(2 * 0.1 / 0.25 + 3 * 1.0 / 2.0) and limit == pytest.approx(2 / need)


def test_bad_profile_is_a_clear_error(tmp_path):
    bad = tmp_path / "p.toml"
    bad.write_text("[latency_s]\nBlob = -1\n")
    proc = run("plan", "--latency-profile", str(bad), "--as-platform", "sitsang")
    assert proc.returncode == 2 and "latency_s.Blob: found -1" in proc.stderr
    proc = run("plan", "--latency-profile", str(bad), "--as-platform", "cray")
    assert proc.returncode == 2 and "--as-platform 'cray'" in proc.stderr
