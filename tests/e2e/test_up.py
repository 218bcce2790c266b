"""`autopower up` as a user runs it: a subprocess of the installed console script.

Everything is bounded: readiness is polled through `autopower status --json`, never slept for.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from autopower.model.loading import load_scenario
from autopower.planner import PlanRequest, plan
from tests.integration.test_forkserver import nice_of_every_thread

AUTOPOWER = os.environ.get("AUTOPOWER_BIN") or str(Path(sys.executable).parent / "autopower")


def env_for(tmp_path: Path) -> dict:
    return {**os.environ, "AUTOPOWER_STATE_DIR": str(tmp_path / "state"), "PYTHONUNBUFFERED": "1"}


def run_cli(args: list[str], env: dict, timeout: float = 30.0) -> subprocess.CompletedProcess:
    return subprocess.run([AUTOPOWER, *args], env=env, capture_output=True, text=True, timeout=timeout)


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead for our purposes
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def wait_until(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")


def test_up_reaches_the_planned_placement(tmp_path):
    result = run_cli(["up", "paper-fig7", "--duration", "6", "--json", "--log-dir", str(tmp_path / "logs")],
                     env_for(tmp_path), timeout=90)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    best = plan(PlanRequest(scenario=load_scenario("paper-fig7")))
    assert summary["ready"] and summary["placement"] == best.allocation
    assert summary["media"] == best.network.media_by_group()
    assert summary["exit_codes"] == {"laptop": 0, "r1": 0, "r2": 0, "r3": 0}
    # startup included; a loaded CI machine misses a few (where, if too many: the robots' sources
    # and the counters that say how late their loops were)
    assert summary["missed_ratio"] < 0.05, {r: (i["sources"], {k: v for k, v in i["counters"].items() if "late" in k
                                                               or "missed" in k or "repeat" in k})
                                            for r, i in summary["robots"].items()}
    assert summary["missed_periods_pct"] == round(100 * summary["missed_ratio"], 2)
    assert bool(summary["warnings"]) == (summary["missed_periods_pct"] > 1.0)  # said whenever it cannot keep up
    sinks = {**summary["basestation"]["sinks"], **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    assert set(sinks) == {c.name for c in load_scenario("paper-fig7").chains}
    assert all(s["received"] > 0 and s["duplicates_total"] == 0 for s in sinks.values())
    for robot, info in summary["robots"].items():
        # over the whole run, startup included, the battery follows the model to within 2 %
        assert abs(info["power_error"]) < 0.02, (robot, info["mean_power_w"], info["predicted_w"])
    assert not list((tmp_path / "state").glob("teams/*"))  # a team that exits leaves nothing behind


def start_up(tmp_path: Path, team: str = "t1", env: dict | None = None,
             extra: tuple[str, ...] = ()) -> tuple[subprocess.Popen, dict, dict]:
    env = env or env_for(tmp_path)
    proc = subprocess.Popen([AUTOPOWER, "up", "paper-fig7", "--team", team, "--log-dir", str(tmp_path / f"logs-{team}"),
                             *extra], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    session_file = Path(env["AUTOPOWER_STATE_DIR"]) / "teams" / team / "session.json"
    session = wait_until(lambda: session_file.exists() and json.loads(session_file.read_text()), 30,
                         "up to write its session file")

    def ready():
        if proc.poll() is not None:
            raise AssertionError(f"up exited early: {proc.stderr.read()[-2000:]}")
        status = run_cli(["status", "--team", team, "--json", "--timeout", "2"], env)
        return status.returncode == 0 and json.loads(status.stdout).get("ready")

    wait_until(ready, 60, "the team to be ready")
    return proc, session, env



@pytest.mark.slow
def test_ctrl_c_stops_every_child_and_chain_disable_works(tmp_path):
    proc, session, env = start_up(tmp_path, extra=("--robot-nice", "4"))
    try:
        children = session["children"]
        assert set(children) == {"laptop", "r1", "r2", "r3"} and all(alive(p) for p in children.values())
        # --robot-nice: every thread of every agent is that much nicer, the base station's are not
        own = os.nice(0)
        assert nice_of_every_thread(children["laptop"]) == {own}
        assert all(nice_of_every_thread(children[r]) == {min(19, own + 4)} for r in ("r1", "r2", "r3"))
        result = run_cli(["chain", "disable", "Blob-2"], env)
        assert result.returncode == 0, result.stderr
        snap = json.loads(run_cli(["status", "--json"], env).stdout)
        assert snap["disabled"] == ["Blob-2"] and "Blob-2" not in snap["target"]
        assert run_cli(["chain", "disable", "Nope"], env).returncode != 0
        proc.send_signal(signal.SIGINT)  # what Ctrl-C delivers to the foreground process
        proc.wait(timeout=30)
        assert proc.returncode == 0, proc.stderr.read()[-2000:]
        wait_until(lambda: not any(alive(p) for p in children.values()), 5, "no child left")
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_no_orphans_when_up_is_terminated_or_killed(tmp_path, sig):
    proc, session, _ = start_up(tmp_path)
    children = session["children"]
    proc.send_signal(sig)
    proc.wait(timeout=30)
    # SIGTERM: `up` stops them itself; SIGKILL: they get SIGTERM from the kernel (PR_SET_PDEATHSIG)
    wait_until(lambda: not any(alive(p) for p in children.values()), 15, "every child to exit")


def test_up_records_a_run_that_replay_reads(tmp_path):
    """The user's path: run the team with --record-dir, then `autopower replay` the merged file."""
    env = env_for(tmp_path)
    run_dir = tmp_path / "runs" / "mine"
    result = run_cli(["up", "paper-fig7", "--duration", "6", "--json", "--energy-scale", "0.01",
                      "--record-dir", str(run_dir), "--log-dir", str(tmp_path / "logs")], env, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["recording"] == str(run_dir / "run.rrd") and (run_dir / "run.rrd").stat().st_size > 0
    replay = run_cli(["replay", summary["recording"], "--json"], env, timeout=120)
    assert replay.returncode == 0, replay.stderr[-3000:]
    data = json.loads(replay.stdout)
    assert data["kind"] == "live" and data["scenario"] == "paper-fig7"
    assert set(data["robots"]) == {"r1", "r2", "r3"}
    assert data["duplicated_outputs"] == 0 and data["lost_outputs"] == 0  # no faults: exactly once
    assert abs(data["energy_model_error_pct"]) <= 1.0
    # each robot's links carried statuses, keep-alives and framing beyond its chain packets: measured
    # on its sockets, charged to its radios as `control`, apart from the model's steady state
    for robot, energy in data["energy"]["per_robot"].items():
        sent = energy["control_bytes"]
        assert 0 < sent["sent"] < sent["link_sent"] and 0 < sent["received"] < sent["link_received"], (robot, sent)
        assert energy["overhead_j"]["control"] > 0, robot
        # its process's CPU beyond its component code (Zenoh, the loop, encoding, metering) is the
        # runtime's: charged as `runtime` at the Sitsang's busy-minus-idle power, x50 (its slowdown)
        cpu = energy["cpu_s"]
        assert cpu["runtime"] > 0 and cpu["component"] > 0, (robot, cpu)
        assert energy["overhead_j"]["runtime"] == pytest.approx((2.27 - 1.34) * 50 * cpu["runtime"], rel=0.01), robot


def test_up_runs_the_policy_it_is_given(tmp_path):
    """`--policy static`: the base station process decides with autopower.policies's static policy."""
    result = run_cli(["up", "paper-fig7", "--policy", "static", "--duration", "6", "--json",
                      "--log-dir", str(tmp_path / "logs")], env_for(tmp_path), timeout=90)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["policy"] == "static" and summary["ready"]
    assert "policy: static" in (tmp_path / "logs" / "laptop.log").read_text()
    bad = run_cli(["up", "--policy", "greedy", "--duration", "1"], env_for(tmp_path))
    assert bad.returncode == 2 and "greedy" in bad.stderr and "static" in bad.stderr


@pytest.mark.slow
def test_up_on_a_pipe_prints_status_lines_and_ends_when_every_robot_is_depleted(tmp_path):
    # 0.2 % of the energy: every robot runs dry after ~100 s virtual, ~10 s wall at 10x
    result = run_cli(["up", "paper-fig7", "--energy-scale", "0.002", "--duration", "80",
                      "--log-dir", str(tmp_path / "logs")], env_for(tmp_path), timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()
    status = [l for l in lines if l.startswith("t=") and "batteries:" in l]
    assert status, result.stdout  # stdout is a pipe: plain lines, no live table
    assert any("every robot depleted" in l for l in lines), result.stdout[-2000:]
    assert "\x1b[" not in result.stdout  # no terminal control codes in a log


@pytest.mark.slow
def test_two_teams_on_one_machine_keep_their_own_state(tmp_path):
    env = env_for(tmp_path)
    first, _, _ = start_up(tmp_path, "t1", env)
    second = None
    try:
        second, session2, _ = start_up(tmp_path, "t2", env)
        which = run_cli(["status", "--json"], env)
        assert which.returncode == 2 and which.stderr.strip() == \
            "error: 2 teams are running (t1, t2); choose one with --team NAME"
        assert json.loads(run_cli(["status", "--team", "t2", "--json"], env).stdout)["ready"]
        links = run_cli(["fault", "--team", "t2", "list"], env)
        assert links.returncode == 0, links.stderr
        first.send_signal(signal.SIGINT)
        first.wait(timeout=30)
        assert first.returncode == 0
        assert (tmp_path / "state" / "teams" / "t2" / "session.json").exists()  # t1 took only its own files
        assert not (tmp_path / "state" / "teams" / "t1").exists()
        alone = run_cli(["status", "--json"], env)  # the only team left needs no --team
        assert alone.returncode == 0 and json.loads(alone.stdout)["ready"], alone.stderr
        assert Path(session2["control"]).stat().st_mode & 0o777 == 0o600
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                proc.wait(timeout=30)


@pytest.mark.slow
def test_ctrl_c_stops_up_also_when_started_with_sigint_ignored(tmp_path):
    """A shell without job control starts a background command with SIGINT ignored (`autopower up &`
    in a script, or CI's own runner): `kill -INT` must still stop the team."""
    env = env_for(tmp_path)
    proc = subprocess.Popen([AUTOPOWER, "up", "paper-fig7", "--team", "t1", "--json"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        session_file = Path(env["AUTOPOWER_STATE_DIR"]) / "teams" / "t1" / "session.json"
        session = wait_until(lambda: session_file.exists() and json.loads(session_file.read_text()), 30,
                             "up to write its session file")
        wait_until(lambda: proc.poll() is not None or json.loads(
            run_cli(["status", "--team", "t1", "--json", "--timeout", "2"], env).stdout or "{}").get("ready"),
            60, "the team to be ready")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
        assert json.loads(out)["scenario"] == "paper-fig7"
        assert not any(alive(pid) for pid in session["children"].values())
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
