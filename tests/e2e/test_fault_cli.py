"""`autopower fault ...` against a running `autopower up`, as a user runs them."""

from __future__ import annotations

import json
import signal

from tests.e2e.test_up import env_for, run_cli, start_up, wait_until


def _status(env) -> dict:
    result = run_cli(["status", "--json", "--timeout", "3"], env)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def _handled(env, kind, target, before):
    def check():
        snap = _status(env)
        return next((f for f in snap["faults"][before:] if f["kind"] == kind and f["target"] == target
                     and f["reconfigured_unix"]), None)
    return wait_until(check, 15, f"{kind} {target} handled")


def test_fault_commands_against_a_running_team(tmp_path):
    proc, session, env = start_up(tmp_path)
    try:
        assert session["control"]
        before = len(_status(env)["faults"])
        result = run_cli(["fault", "cut", "r1", "laptop", "--json"], env)
        assert result.returncode == 0, result.stderr
        t_cut = json.loads(result.stdout)["fault"]["t_unix"]
        fault = _handled(env, "link-down", "laptop-r1", before)
        assert fault["detected_unix"] - t_cut <= 1.0
        assert fault["reconfigured_unix"] - t_cut <= 1.5
        assert _status(env)["robots"]["r1"]["present"]  # kept through a relay

        # faults work while links are cut: the control channel is not a Zenoh link
        assert run_cli(["fault", "heal", "r1", "laptop"], env).returncode == 0
        wait_until(lambda: not _status(env)["links_down"], 15, "the link back in the plan")

        result = run_cli(["fault", "radio", "r3", "--laptop", "gsm", "--robot", "bluetooth"], env)
        assert result.returncode == 0, result.stderr
        snap = _status(env)
        assert ["r3", "laptop", "gsm"] in snap["links"] or ["laptop", "r3", "gsm"] in snap["links"]

        for args, needle in ([["fault", "kill", "r9"], "unknown robot 'r9'"],
                             [["fault", "cut", "r1", "nowhere"], "unknown node 'nowhere'"]):
            bad = run_cli(args, env)
            assert bad.returncode == 2 and needle in bad.stderr and len(bad.stderr.strip().splitlines()) == 1

        before = len(_status(env)["faults"])
        t_kill = json.loads(run_cli(["fault", "kill", "r2", "--json"], env).stdout)["fault"]["t_unix"]
        fault = _handled(env, "node-left", "r2", before)
        assert fault["detected_unix"] - t_kill <= 1.0 and fault["reconfigured_unix"] - t_kill <= 1.5

        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
        assert proc.returncode == 0, proc.stderr.read()[-2000:]  # a killed robot is not an error of `up`
    finally:
        if proc.poll() is None:
            proc.kill()


def test_fault_without_a_running_team_is_one_clear_error(tmp_path):
    result = run_cli(["fault", "cut", "r1", "laptop"], env_for(tmp_path))
    assert result.returncode == 2
    assert "no running team" in result.stderr and len(result.stderr.strip().splitlines()) == 1
