"""`autopower replay`: summaries of simulated recordings, what-ifs, clear errors, the web viewer."""

from __future__ import annotations

import json
import os

import pytest

from autopower.cli.replay import main as replay_main
from autopower.errors import AutoPowerError, RecordingError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import load_events
from autopower.recording.replay import load, summarize
from autopower.recording.telemetry import Telemetry
from autopower.recording.what_if import recorded_state, what_if
from autopower.simulation.simulator import simulate

os.environ.setdefault("RERUN_ANALYTICS", "0")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    path = tmp_path_factory.mktemp("sim") / "sim.rrd"
    sc = load_scenario("paper-fig7")
    events = load_events("link-cuts", sc)
    with Telemetry(path, kind="simulation", properties={"scenario": sc.name, "policy": "rebalance",
                                                        "accounting": sc.accounting,
                                                        "topology": sc.network_spec.topology}) as tel:
        result = simulate(sc, events, policy="rebalance", telemetry=tel)
    return path, result


def run_cli(capsys, *args):
    with pytest.raises(SystemExit) as exit_info:
        replay_main([str(a) for a in args])
        raise SystemExit(0)
    out = capsys.readouterr()
    return exit_info.value.code, out.out, out.err


def test_summary_of_a_simulation_matches_the_simulator(simulated):
    path, result = simulated
    s = summarize(load(path), path)
    assert s["kind"] == "simulation" and s["scenario"] == "paper-fig7" and s["policy"] == "rebalance"
    assert s["mission"]["end_s"] == pytest.approx(result.lifetime_s)
    assert s["first_dry"]["robot"] == result.first_dry and not s["first_dry"]["projected"]
    assert s["first_dry"]["at_s"] == pytest.approx(result.lifetime_s)
    for robot, final in result.final_energies_j.items():
        assert s["robots"][robot]["final_j"] == pytest.approx(final, abs=1e-6)
    assert s["migrations"]["count"] == len(result.migrations)
    cuts = [f for f in s["faults"] if f["kind"] == "cut"]
    assert {p for f in cuts for p in f["parts"]} >= {"r1-laptop", "r2-laptop", "r3-laptop"}
    assert all(f["detected_mission_s"] == 0.0 and f["reconfigured_mission_s"] == 0.0 for f in cuts)
    assert all(f["detected_wall_s"] is None for f in cuts)  # a simulation has no wall clock
    # the battery also pays for migrations, which the steady-state model does not: a small error
    assert s["energy_model_error_pct"] is not None and abs(s["energy_model_error_pct"]) < 5
    assert not s["outputs"]["recorded"] and s["ok"]
    inv = {i["name"]: i["ok"] for i in s["invariants"]}
    assert inv["battery never increases"] is True  # the fresh battery pack is an event, exempt


def test_json_output_is_one_object(simulated, capsys):
    path, result = simulated
    code, out, err = run_cli(capsys, path, "--json")
    assert code == 0, err
    doc = json.loads(out)
    for key in ("recording", "kind", "mission", "robots", "first_dry", "migrations", "faults", "energy",
                "outputs", "invariants", "ok", "lost_outputs", "duplicated_outputs", "energy_model_error_pct"):
        assert key in doc
    assert doc["migrations"]["count"] == len(result.migrations)


def test_text_output(simulated, capsys):
    path, _ = simulated
    code, out, _ = run_cli(capsys, path)
    assert code == 0
    assert "first to run dry" in out and "invariants:" in out and "faults:" in out


def test_what_if_from_the_recorded_state(simulated, capsys):
    path, _ = simulated
    rec = load(path)
    state = recorded_state(rec, 7300.0)
    assert state["allocation"]["Loc-1"] == "r1"  # all cut from the base station at 7200 s
    assert all(e < 64000 for e in state["energies_j"].values())
    w = what_if(rec, at_s=7300.0)
    assert set(w["plan"]["dropped_chains"]) == {"Blob-2", "Blob-3"}  # the sink is unreachable
    assert w["plan"]["lifetime_s"] > 0 and w["recorded"]["lifetime_s"] > 0
    w2 = what_if(rec, at_s=100.0, energies={"r1": 1000.0}, disable=("Blob-3",), accounting="physical")
    assert "Blob-3" not in w2["plan"]["allocation"] and w2["plan"]["bottleneck"] == "r1"
    code, out, err = run_cli(capsys, path, "--json", "--what-if", "--at", 100, "--topology", "relay",
                             "--policy", "static")
    assert code == 0, err
    doc = json.loads(out)["what_if"]
    assert doc["at_s"] == 100.0 and doc["policy"]["name"] == "static" and doc["policy"]["lifetime_s"] > 0
    code, out, err = run_cli(capsys, path, "--what-if", "--energy", "r9=5")
    assert code == 2 and "r9" in err and "Traceback" not in err
    code, out, err = run_cli(capsys, path, "--at", 5)
    assert code == 2 and "--what-if" in err


def test_what_if_with_the_control_plane_charged(simulated, capsys):
    """The same recorded state, the team's statuses and keep-alives charged: the recorded
    allocation lives shorter, and so does the best plan (they are never free)."""
    path, _ = simulated
    free = what_if(load(path), at_s=100.0)
    charged = what_if(load(path), at_s=100.0, control_plane=True)
    assert charged["settings"]["control_plane"] and not free["settings"]["control_plane"]
    assert charged["recorded"]["lifetime_s"] < free["recorded"]["lifetime_s"]
    assert charged["plan"]["lifetime_s"] < free["plan"]["lifetime_s"]
    code, out, err = run_cli(capsys, path, "--json", "--what-if", "--at", 100, "--control-plane")
    assert code == 0, err
    assert json.loads(out)["what_if"]["recorded"]["lifetime_s"] == pytest.approx(charged["recorded"]["lifetime_s"])
    code, out, err = run_cli(capsys, path, "--control-plane")
    assert code == 2 and "--what-if" in err


@pytest.mark.parametrize("kind", ["missing", "empty", "garbage", "truncated", "foreign"])
def test_bad_files_get_one_clear_error(kind, simulated, tmp_path, capsys):
    path = tmp_path / f"{kind}.rrd"
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "garbage":
        path.write_bytes(os.urandom(4096))
    elif kind == "truncated":
        path.write_bytes(simulated[0].read_bytes()[:3000])
    elif kind == "foreign":
        import rerun as rr

        stream = rr.RecordingStream("someone-else", recording_id="foreign")
        stream.save(str(path))
        stream.log("points", rr.Points2D([[0, 0]]))
        stream.disconnect()
    with pytest.raises(RecordingError) as info:
        load(path)
    assert str(path) in str(info.value) and isinstance(info.value, AutoPowerError)
    code, out, err = run_cli(capsys, path, "--json")
    assert code == 2 and json.loads(out) == {"error": str(info.value), "exit_code": 2}  # the JSON contract
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err


def test_serve_opens_the_viewer_on_loopback_and_stops_it(simulated, capsys):
    path, _ = simulated
    code, out, err = run_cli(capsys, path, "--json", "--serve", "--serve-seconds", 0.5)
    assert code == 0, err
    json.loads(out)  # stdout stays one JSON object; the viewer's messages go to stderr
    line = next(l for l in err.splitlines() if l.startswith("viewer: "))
    assert line.startswith("viewer: http://127.0.0.1:")
    url = line.split()[1]
    assert url.endswith("&renderer=webgl")  # no GPU needed (WebGPU fails without one)
    pid = int(line.split("(pid ")[1].split(";")[0])
    assert "viewer stopped" in err
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_a_real_process_exits_2_without_a_traceback(tmp_path):
    import subprocess
    import sys

    bad = tmp_path / "corrupt.rrd"
    bad.write_bytes(b"RRF2" + os.urandom(200))
    done = subprocess.run([sys.executable, "-m", "autopower.cli.replay", str(bad)], capture_output=True,
                          text=True, timeout=60, env={**os.environ, "RERUN_ANALYTICS": "0"})
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.startswith(f"error: {bad}") and "Traceback" not in done.stderr


def test_a_killed_robot_is_not_waited_for_by_the_plan_made_before_it_was_known_gone():
    """Demo run 2026-11-24: r2 SIGKILLed at t=79.7; its links to r1 and r3 were reported down first,
    and that plan (epoch 22) still had r2. r1 and r3 ran the plan without r2 (epoch 24) at 81.1;
    r2 ran anything again only once restarted, at 106.2. The team was reconfigured at 81.1."""
    import math

    from autopower.recording.replay import _reconfiguration

    class Rec:
        properties = {"basestation": "laptop"}
        epochs = {"r1": ([80.31, 81.08], [22.0, 24.0]), "r3": ([80.31, 81.1], [22.0, 24.0]),
                  "r2": ([106.23], [24.0])}

        def series(self, entity):
            robot = entity.split("/")[1]
            return self.epochs.get(robot, ([], [])) if entity.endswith("/plan_epoch") else ([], [])

    plans = [(80.0, 22, ["laptop", "r1", "r2", "r3"]), (80.9, 24, ["laptop", "r1", "r3"])]
    assert _reconfiguration(Rec(), "live", 79.7, math.inf, plans, [], [], [], {"r2"}) == (81.1, "plan epoch 24")
    # a cut (nobody killed) still waits for every robot of the first plan's network
    assert _reconfiguration(Rec(), "live", 79.7, math.inf, plans, [], [], []) == (106.23, "plan epoch 22")


def test_the_robot_table_prints_no_negative_zero_and_keeps_its_columns(simulated):
    """A battery metered a fraction of a joule past empty reads 0 J, not "-0"; the projected mark
    does not shift its row against the others."""
    from autopower.recording.report import render_text

    path, _ = simulated
    s = summarize(load(path), path)
    robots = list(s["robots"])
    s["robots"][robots[0]].update(final_j=-0.3, ran_dry_at_s=100.0, lifetime_s=100.0)
    s["robots"][robots[1]].update(final_j=12.6, ran_dry_at_s=None, lifetime_s=4321.0)
    rows = {line.split()[0]: line for line in render_text(s).splitlines() if line.split()[:1] == [robots[0]]
            or line.split()[:1] == [robots[1]]}
    assert rows[robots[0]].split()[2] == "0"
    assert rows[robots[1]].split()[2] == "13" and rows[robots[1]].endswith("4,321.0 s*")
    assert rows[robots[0]].endswith("100.0 s ")
    assert len(rows[robots[0]]) == len(rows[robots[1]])


def test_each_robots_energy_is_split_into_the_models_steady_state_and_each_overhead(simulated):
    from autopower.recording.report import render_text

    path, _ = simulated
    s = summarize(load(path), path)
    for per in s["energy"]["per_robot"].values():
        per["overhead_j"] = {"migration": 0.0, "recovery": 0.0, "control": 0.0, "runtime": 0.0}
    robot = next(iter(s["energy"]["per_robot"]))
    per = s["energy"]["per_robot"][robot]
    per["metered_j"] = 100.0
    per["overhead_j"].update(control=1.25, runtime=7.5)
    text = render_text(s)
    head = next(line for line in text.splitlines() if line.strip().startswith("split"))
    assert head.split() == ["split", "chains", "J", "control", "J", "runtime", "J"]  # only the overheads there are
    row = next(line for line in text.splitlines() if line.strip().startswith(f"{robot}:"))
    cols = dict(zip([w for w in head.split() if w != "J"], row.split(), strict=True))
    assert cols["chains"] == "91.25" and cols["control"] == "1.25" and cols["runtime"] == "7.50"


def test_the_model_is_checked_apart_within_reconfigurations_and_in_steady_running(tmp_path):
    """A stage moves onto r1 at t = 50 (its model power 1 W -> 2 W); the runtime carries the move out
    over its reaction time, so r1 draws the old power 2.5 s longer (the inputs of those seconds ran
    where they were). A steady-state model cannot follow that: the whole run disagrees by 2.5 J, and
    outside the reconfiguration window (two status periods of wall time at the run's x5) meter and
    model agree exactly. A disagreement outside every window is not hidden by one."""
    from autopower.recording.recorder import tag_event
    from autopower.recording.telemetry import DECISIONS
    from autopower.recording.transitions import reaction_s

    def recording(name: str, drift_w: float) -> dict:
        path = tmp_path / name
        with Telemetry(path, kind="live", properties={"scenario": "paper-fig7"}) as tel:
            tel.text(DECISIONS, 0.0, tag_event("plan epoch 1", type="plan", speed=5.0, epoch_unix=0.0))
            battery = 1000.0
            tel.scalar("robots/r1/model_w", 0.0, 1.0)
            tel.scalar("robots/r1/model_w", 50.0, 2.0)
            for i in range(201):
                t = i * 0.5
                tel.battery(t, "r1", battery)
                battery -= 0.5 * ((1.0 if t < 52.5 else 2.0) + drift_w * (t >= 80.0))
        return summarize(load(path), path)

    from autopower.agent.process import AgentConfig
    from autopower.recording.transitions import STATUS_PERIOD_S

    assert STATUS_PERIOD_S == AgentConfig.status_period_s  # the runtime's, which the window is made of
    s = recording("lag.rrd", 0.0)
    assert reaction_s(5.0) == s["energy"]["transitions"]["window_s"] == 5.0
    assert s["energy"]["transitions"]["windows"] == [[50.0, 55.0]]
    assert s["energy_model_error_pct"] == pytest.approx(-2.5 / 150.0 * 100)  # 147.5 J metered, 150 J modelled
    assert s["energy_steady_error_pct"] == pytest.approx(0.0, abs=1e-9)
    assert s["energy"]["transitions"]["transition_j"] == pytest.approx(-2.5)
    assert s["energy"]["per_robot"]["r1"]["transition_j"] == pytest.approx(-2.5)
    t = s["energy"]["transitions"]
    assert t["steady_model_j"] == pytest.approx(140.0) and t["steady_metered_j"] == pytest.approx(140.0)
    assert t["covered_s"] == pytest.approx(5.0)
    # a meter drifting from the model in steady running (20 s at +0.1 W from t = 80) shows outside them
    drifted = recording("drift.rrd", 0.1)
    assert drifted["energy_steady_error_pct"] == pytest.approx(2.0 / (150.0 - 10.0) * 100)  # the window modelled 10 J
