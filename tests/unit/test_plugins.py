"""Components of one's own: the public API, plug-ins named in scenarios or by entry points, and
`autopower profile --component`; loading errors are one line naming the scenario file and line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

import autopower
from autopower.chains.plugins import register_scenario_components
from autopower.chains.registry import component_types, make_component, make_source, unregister_component_type
from autopower.errors import ScenarioError
from autopower.model.loading import load_scenario
from autopower.protocol import Keys, StageFailed, encode
from autopower.recording.recorder import Recorder, parse_event
from autopower.recording.telemetry import MIGRATIONS, Telemetry, read_recording
from autopower.runtime.bus import InMemoryHub

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "examples" / "motion_demo"
MOTION = (EXAMPLE / "motion.toml").read_text()
AUTOPOWER = shutil.which("autopower", path=str(Path(sys.executable).parent)) or "autopower"

PLUGS = {
    "good.py": '''
        class Camera:
            def __init__(self, robot, seed):
                self.robot, self.seed = robot, seed
            def produce(self, seq):
                return bytes([seq % 256]) * 3084

        class Detector:
            SOURCE = Camera
            def __init__(self, robot: str, seed: int):
                self.last = b""
            def run(self, payload):
                self.last = payload[:4]
                return b"ok" + self.last
            def export_state(self):
                return self.last
            def import_state(self, state):
                self.last = state
        ''',
    "not_component.py": '''
        class Detector:
            def __init__(self, robot, seed): pass
            def process(self, payload): return payload
        ''',
    "bad_ctor.py": '''
        class Detector:
            def __init__(self, robot, seed, model_path): pass
            def run(self, payload): return payload
        ''',
    "half_state.py": '''
        class Detector:
            def __init__(self, robot, seed): pass
            def run(self, payload): return payload
            def export_state(self): return b""
        ''',
    "broken_import.py": '''
        import math
        RADIUS = math.sqrt(-1)
        ''',
}


@pytest.fixture()
def plugs(tmp_path, monkeypatch):
    package = tmp_path / "myplugs"
    package.mkdir()
    (package / "__init__.py").write_text("")
    for name, body in PLUGS.items():
        (package / name).write_text(textwrap.dedent(body))
    monkeypatch.syspath_prepend(str(tmp_path))
    names = set(component_types())
    yield tmp_path
    for name in set(component_types()) - names:
        unregister_component_type(name)
    for module in [m for m in sys.modules if m.startswith("myplugs")]:
        del sys.modules[module]


def scenario_with(tmp_path: Path, implementation: str | None, source: str | None = "myplugs.good:Camera") -> Path:
    lines = [line for line in MOTION.splitlines()
             if not line.startswith(("implementation =", "source = \"motion_demo"))]
    text = "\n".join(lines) + "\n"
    extra = "".join(f'{key} = "{value}"\n' for key, value in (("implementation", implementation), ("source", source))
                    if value is not None)
    text = text.replace("[components.Motion]\n", "[components.Motion]\n" + extra)
    path = tmp_path / "mission.toml"
    path.write_text(text)
    return path


def line_of(path: Path, start: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if line.startswith(start))


def run_cli(*args: str, pythonpath: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(pythonpath)}
    return subprocess.run([AUTOPOWER, *args], capture_output=True, text=True, timeout=120, env=env)


def test_the_public_api_is_the_builtin_contract():
    for name, methods in (("Component", ["run"]), ("StatefulComponent", ["export_state", "import_state"]),
                          ("Source", ["produce"]), ("ScoredSource", ["ground_truth"])):
        protocol = getattr(autopower, name)
        assert name in autopower.__all__ and protocol.__doc__
        assert all(getattr(protocol, m).__doc__ for m in methods)
    blob, loc = make_component("Blob", "r2", 1), make_component("Loc", "r2", 1)
    assert isinstance(blob, autopower.Component) and isinstance(loc, autopower.StatefulComponent)
    assert isinstance(make_source("Loc", "r2", 1), autopower.ScoredSource)
    sys.path.insert(0, str(EXAMPLE))
    try:
        from motion_demo import GreyCamera, MotionDetector
    finally:
        sys.path.remove(str(EXAMPLE))
    assert isinstance(MotionDetector("r1", 0), autopower.StatefulComponent)
    assert isinstance(GreyCamera("r1", 0), autopower.ScoredSource)
    assert autopower.ENTRY_POINT_GROUP == "autopower.components"


def test_a_scenario_plugin_is_registered_and_built_on_demand(plugs):
    scenario = load_scenario(scenario_with(plugs, "myplugs.good:Detector"))
    spec = scenario.components["Motion"]
    assert (spec.implementation, spec.source) == ("myplugs.good:Detector", "myplugs.good:Camera")
    assert register_scenario_components(scenario.components) == ["Motion"]
    assert register_scenario_components(scenario.components) == []  # again: the same classes, nothing to do
    component, source = make_component("Motion", "r2", 7), make_source("Motion", "r2", 7)
    assert component.run(source.produce(5)) == b"ok" + bytes([5]) * 4


@pytest.mark.parametrize("implementation, key, expected", [
    ("nowhere.motion:Detector", "implementation", "module 'nowhere' not found; install the package"),
    ("myplugs.good:Detecter", "implementation", "module 'myplugs.good' has no attribute 'Detecter'"),
    ("myplugs.not_component:Detector", "implementation", "Detector is not a component: it has no run(self, payload"),
    ("myplugs.bad_ctor:Detector", "implementation",
     "Detector(robot, seed, model_path) cannot be constructed as Detector(robot, seed)"),
    ("myplugs.half_state:Detector", "implementation", "Detector has export_state but no import_state"),
    ("myplugs.broken_import:Detector", "implementation", "importing 'myplugs.broken_import' failed: ValueError"),
    ("myplugs.good:Camera", "implementation", "Camera is not a component"),
])
def test_a_bad_plugin_is_one_line_naming_file_and_line(plugs, implementation, key, expected):
    path = scenario_with(plugs, implementation)
    with pytest.raises(ScenarioError) as err:
        register_scenario_components(load_scenario(path).components)
    message = str(err.value)
    assert message.startswith(f"{path}:{line_of(path, key + ' =')}: components.Motion.{key}")
    assert expected in message and "\n" not in message


def test_a_source_that_is_not_one_names_the_source_line(plugs):
    path = scenario_with(plugs, "myplugs.good:Detector", source="myplugs.good:Detector")
    with pytest.raises(ScenarioError, match=rf"^{path}:{line_of(path, 'source =')}: components.Motion.source: "
                                            r"Detector is not a source: it has no produce"):
        register_scenario_components(load_scenario(path).components)


def test_half_a_plugin_and_a_malformed_path_fail_at_load(plugs):
    with pytest.raises(ScenarioError, match="implementation without source"):
        load_scenario(scenario_with(plugs, "myplugs.good:Detector", source=None))
    with pytest.raises(ScenarioError, match=r"components.Motion.implementation: found 'myplugs.good.Detector'; "
                                            r"expected \"package.module:ClassName\""):
        load_scenario(scenario_with(plugs, "myplugs.good.Detector"))


def test_the_cli_refuses_a_bad_plugin_before_starting_anything(plugs):
    path = scenario_with(plugs, "myplugs.bad_ctor:Detector")
    for command in (["plan", str(path)], ["check", str(path)], ["up", str(path), "--duration", "5"]):
        out = run_cli(*command, pythonpath=plugs)
        assert out.returncode == 2, (command, out.stderr)
        assert out.stdout == ""
        [line] = out.stderr.strip().splitlines()
        assert line.startswith(f"error: {path}:{line_of(path, 'implementation =')}: components.Motion.implementation")
    assert run_cli("plan", str(scenario_with(plugs, "myplugs.good:Detector")), pythonpath=plugs).returncode == 0
    # a component with no code at all: fine to plan, refused to run
    nameless = scenario_with(plugs, None, source=None)
    assert run_cli("plan", str(nameless), pythonpath=plugs).returncode == 0
    out = run_cli("up", str(nameless), "--duration", "5", pythonpath=plugs)
    assert out.returncode == 2 and out.stderr.startswith(f"error: {nameless}:{line_of(nameless, 'latency_s =')}: "
                                                         f"components.Motion: no code for this component")


def test_an_installed_package_registers_by_entry_point(plugs):
    dist = plugs / "myplugs-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: myplugs\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[autopower.components]\nMotion = myplugs.good:Detector\n")
    scenario = load_scenario(scenario_with(plugs, None, source=None))  # no implementation line at all
    assert scenario.components["Motion"].implementation is None
    assert register_scenario_components(scenario.components) == ["Motion"]
    assert make_component("Motion", "r1", 0).run(make_source("Motion", "r1", 0).produce(2)) == b"ok\x02\x02\x02\x02"


def test_profile_measures_a_plugin_and_prints_the_block_to_paste(tmp_path):
    out = run_cli("profile", "--component", "motion_demo.motion:MotionDetector", "--source",
                  "motion_demo.camera:GreyCamera", "--name", "Motion", "--runs", "20", "--factor", "laptop=1",
                  "--factor", "sitsang=40", "--json", pythonpath=EXAMPLE)
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    measured = data["measured"]
    assert measured["output_bytes_max"] == 20 and measured["input_bytes_max"] == 3084
    assert measured["state_bytes_max"] == 3076  # the previous frame + its tag
    block = tomllib.loads(data["block"])["components"]["Motion"]
    assert block["latency_s"]["sitsang"] == pytest.approx(40 * measured["latency_median_s"], rel=1e-2)
    assert block["latency_s"]["laptop"] == pytest.approx(measured["latency_median_s"], rel=1e-2)
    # pasted into the example scenario in place of its own block, it loads and registers
    text = MOTION[:MOTION.index("[components.Motion]")] + data["block"] + "\n\n" + MOTION[MOTION.index("[[chains]]"):]
    path = tmp_path / "pasted.toml"
    path.write_text(text)
    plain = run_cli("profile", "--component", "motion_demo.motion:MotionDetector", "--runs", "5", pythonpath=EXAMPLE)
    assert plain.returncode == 0 and plain.stdout.startswith("[components.MotionDetector]")
    assert "median" in plain.stderr  # the measurement itself goes to stderr, the block to stdout
    assert run_cli("plan", str(path), pythonpath=EXAMPLE).returncode == 0
    bad = run_cli("profile", "--component", "motion_demo.motion:Nope", pythonpath=EXAMPLE)
    assert bad.returncode == 2 and "has no attribute 'Nope'" in bad.stderr and len(bad.stderr.splitlines()) == 1


def test_a_failed_stage_is_in_the_recording_with_its_text(tmp_path):
    rec = Recorder(Telemetry(tmp_path / "r2.rrd", kind="live"), "r2", clock=lambda: 12.5)
    bus = rec.tap(InMemoryHub().bus("r2"))
    bus.publish(Keys("t").inbox, encode(StageFailed(stage="Motion-2", generation=3, node="r2", what="raised",
                                                    detail="run(seq 10): ValueError: frame 10", running=False)))
    rec.close()
    events = [parse_event(line) for _t, line, _level in read_recording(tmp_path / "r2.rrd").log(MIGRATIONS)]
    [(text, payload)] = [(t, p) for t, p in events if p and p.get("type") == "stage-failed"]
    assert text == "Motion-2 failed on r2 (raised: run(seq 10): ValueError: frame 10); stopped"
    assert payload["detail"] == "run(seq 10): ValueError: frame 10" and payload["running"] is False


def test_a_plugin_cannot_take_a_builtin_name(plugs):
    path = scenario_with(plugs, "myplugs.good:Detector")
    path.write_text(path.read_text().replace("Motion", "Blob"))
    with pytest.raises(ScenarioError, match=rf"^{path}:\d+: components.Blob: the name 'Blob' is already a component "
                                            r"type \(CMVision-style colour blob finder.*\); give yours another name"):
        register_scenario_components(load_scenario(path).components)
