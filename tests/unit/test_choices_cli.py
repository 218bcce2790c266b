"""Quality variants and DVFS levels as a user sees them: the installed `autopower` command's
Pareto front (text and --json) and one-line, exit-2 errors naming file:line:field."""

import json
import subprocess
import sys
from importlib import resources
from pathlib import Path

import pytest

AUTOPOWER = str(Path(sys.executable).parent / "autopower")
VARIANTS = (resources.files("autopower.scenarios") / "paper-variants-dvfs.toml").read_text()


def run(*args):
    return subprocess.run([AUTOPOWER, *args], capture_output=True, text=True, timeout=300)


def test_pareto_front_json_through_the_installed_command():
    out = run("analyze", "paper-variants", "--accounting", "physical", "--pareto", "--json")
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert d["scenario"] == "paper-variants" and d["accounting"] == "physical" and d["has_variants"]
    front = d["front"]
    assert len(front) == 3
    assert [p["quality"] for p in front] == pytest.approx([0.84, 0.92, 1.0])
    lives = [p["lifetime_s"] for p in front]
    assert lives == sorted(lives, reverse=True)
    # every point is a plan the planner would give at that quality: the top one is `plan`'s
    plan = json.loads(run("plan", "paper-variants", "--accounting", "physical", "--json", "--no-bound").stdout)
    assert plan["lifetime_s"] == lives[0] and plan["variants"] == front[0]["variants"]
    assert plan["quality"] == pytest.approx(front[0]["quality"])


def test_pareto_front_text():
    out = run("analyze", "paper-variants-dvfs", "--accounting", "physical", "--pareto")
    assert out.returncode == 0, out.stderr
    assert "lifetime against quality" in out.stdout and "Blob-2=1fps" in out.stdout and "100MHz" in out.stdout


def test_plan_prints_variants_and_levels():
    out = run("plan", "paper-variants-dvfs", "--accounting", "physical", "--no-bound")
    assert out.returncode == 0, out.stderr
    assert "Blob-2 runs variant 1fps" in out.stdout and "r1 runs at 100MHz" in out.stdout
    assert "mean quality 0.840" in out.stdout


@pytest.mark.parametrize("old, new, where", [
    ('[components.Loc.variants."300p"]\nquality = 0.85', '[components.Loc.variants."300p"]\nquality = 1.5',
     "components.Loc.variants.300p.quality: found 1.5; expected a score in (0, 1]"),
    ('latency_factor = 4.0', 'latency_factor = 0.5',
     "platforms.sitsang.levels.100MHz.latency_factor: found 0.5; expected a factor >= 1"),
    ('idle_w = 1.2548\nbusy_w = 1.3924', 'idle_w = 1.2548\nbusy_w = 1.0',
     "platforms.sitsang.levels.100MHz.busy_w: busy_w 1.0 < idle_w 1.2548"),
    ('message_bytes = [230415, 200] # 320x240 RGB PPM in, blob list out\n\n[[chains]]\nname = "Blob-3"',
     'message_bytes = [230415, 200]\nmin_quality = 1.2\n\n[[chains]]\nname = "Blob-3"',
     "chains[3].min_quality: found 1.2 but the best variant of Blob scores 1.0"),
    ('[[chains]]\nname = "Loc-1"', '[mission]\nquality_weight = 2\n\n[[chains]]\nname = "Loc-1"',
     "mission.quality_weight: found 2.0; expected a weight in [0, 1]"),
    ('parameters = { n_particles = 100 }', 'parameters = { n_particles = 100 }\nperiod = 3',
     "components.Loc.variants.100p.period: unknown key"),
])
def test_bad_variants_and_levels_are_one_line_exit_2(tmp_path, old, new, where):
    assert old in VARIANTS
    path = tmp_path / "bad.toml"
    path.write_text(VARIANTS.replace(old, new, 1))
    out = run("check", str(path))
    assert out.returncode == 2, out.stdout + out.stderr
    err = out.stderr.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert f"{path}:" in err and where in err
    line = int(err.split(f"{path}:")[1].split(":")[0])
    key = where.split(":")[0].split(".")[-1].split("[")[0]
    assert path.read_text().splitlines()[line - 1].startswith(key)  # the line of the offending field


def test_quality_command_declared_against_measured():
    out = run("quality", "paper-variants", "--duration", "20", "--json")
    assert out.returncode == 0, out.stderr
    rows = {(r["component"], r["variant"]): r for r in json.loads(out.stdout)["variants"]}
    assert set(rows) == {("Loc", "1000p"), ("Loc", "300p"), ("Loc", "100p"), ("Blob", "4fps"), ("Blob", "2fps"),
                         ("Blob", "1fps")}
    assert rows[("Blob", "2fps")]["declared"] == 0.8 and rows[("Blob", "2fps")]["outputs"] == 40
    assert rows[("Blob", "1fps")]["measured"] < rows[("Blob", "2fps")]["measured"] < rows[("Blob", "4fps")]["measured"]
    bad = run("quality", "paper-variants", "--duration", "-1")
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
