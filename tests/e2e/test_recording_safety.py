"""Recordings are never lost silently: refused up front, failures stop the team, merge after a crash."""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import time

import pytest

from tests.e2e.test_up import AUTOPOWER, alive, env_for, run_cli, wait_until


def test_an_unusable_record_dir_is_refused_before_anything_starts(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    started = time.monotonic()
    result = run_cli(["up", "--record-dir", str(blocker / "run"), "--duration", "5"], env_for(tmp_path))
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"error: --record-dir {blocker / 'run'}: cannot write there (Not a directory); "
        "choose a directory you can write to"]
    assert time.monotonic() - started < 15 and not (tmp_path / "state" / "teams").exists()


def _start(tmp_path, record_dir, *extra):
    env = env_for(tmp_path)
    proc = subprocess.Popen([AUTOPOWER, "up", "paper-fig7", "--team", "rec", "--record-dir", str(record_dir),
                             "--log-dir", str(tmp_path / "logs"), *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def ready():
        if proc.poll() is not None:
            raise AssertionError(f"up exited early: {proc.stderr.read()[-2000:]}")
        status = run_cli(["status", "--team", "rec", "--json", "--timeout", "2"], env)
        return status.returncode == 0 and json.loads(status.stdout).get("ready")

    wait_until(ready, 60, "the team to be ready")
    session = json.loads((tmp_path / "state" / "teams" / "rec" / "session.json").read_text())
    return proc, session


@pytest.mark.slow
def test_a_recording_that_fails_mid_run_stops_the_team_and_says_so(tmp_path):
    record_dir = tmp_path / "rec"
    proc, session = _start(tmp_path, record_dir, "--json", "--duration", "120")
    try:
        shutil.rmtree(record_dir)  # the disk is gone from under the run
        out, err = proc.communicate(timeout=40)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, err[-2000:]
    summary = json.loads(out)
    assert "recording failed during the run" in summary["recording_error"] and summary["recording"] is None
    assert summary["wall_s"] < 100  # stopped for it, not at the end of --duration
    assert err.strip().splitlines()[-1].startswith("error: the recording failed (cannot write to")
    assert not any(alive(p) for p in session["children"].values())


@pytest.mark.slow
def test_after_up_is_killed_recording_merge_builds_run_rrd(tmp_path):
    record_dir = tmp_path / "rec"
    proc, session = _start(tmp_path, record_dir)
    time.sleep(3)  # something worth recording
    proc.send_signal(signal.SIGKILL)  # no chance to merge
    proc.wait(timeout=30)
    wait_until(lambda: not any(alive(p) for p in session["children"].values()), 15, "every child to exit")
    assert not (record_dir / "run.rrd").exists()
    env = env_for(tmp_path)
    merged = run_cli(["recording", "merge", str(record_dir)], env, timeout=120)
    assert merged.returncode == 0, merged.stderr
    assert (record_dir / "run.rrd").stat().st_size > 0
    assert "merged 4 recordings (laptop.rrd, r1.rrd, r2.rrd, r3.rrd)" in merged.stdout
    replay = run_cli(["replay", str(record_dir / "run.rrd"), "--json"], env, timeout=120)
    assert replay.returncode == 0, replay.stderr[-2000:]
    assert json.loads(replay.stdout)  # a recording replay can read
    # the dead team's files are recognised and removed by the next command
    assert run_cli(["status", "--team", "rec"], env).returncode == 2
    assert not (tmp_path / "state" / "teams" / "rec").exists()
