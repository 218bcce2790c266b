"""`autopower testbed up|down` as a user runs them: real namespaces, shaped veth links, mTLS + ACL.

Needs root (CI runs as root on this machine kind). Without it these tests fail with that reason
rather than pass. Every namespace a test creates is removed in a finalizer, also on failure.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess

import pytest

from autopower.launch.netns import PREFIX, list_namespaces, remove_namespaces
from tests.e2e.test_up import AUTOPOWER, env_for, run_cli, wait_until

pytestmark = pytest.mark.slow


@pytest.fixture
def root():
    if os.geteuid() != 0:
        pytest.fail("the testbed tests need root (network namespaces); CI runs them as root")


def ours() -> set[str]:
    return {n for n in list_namespaces() if n.startswith(PREFIX)}


@pytest.fixture
def clean(root, tmp_path):
    """After the test, remove what its own testbed runs left and fail if there was anything.

    Only runs recorded under this test's directory count (a run deletes its record once it has
    removed its namespaces): other test sessions on this machine may be running testbeds too,
    and their namespaces are none of ours.
    """
    yield

    records = list(tmp_path.rglob("testbed/*.json"))
    leftovers = set()
    for record in records:
        try:
            leftovers |= set(json.loads(record.read_text()).get("namespaces", [])) & ours()
        except (OSError, json.JSONDecodeError):
            continue
    remove_namespaces(leftovers)  # never leave a namespace behind, even when the test failed
    assert not leftovers, f"namespaces left behind: {sorted(leftovers)}"


def stop(proc) -> None:
    """Stop `testbed up` the way a user does (Ctrl-C), so it removes what it made; kill if it hangs."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def start_testbed(tmp_path, *args):
    env = env_for(tmp_path)
    proc = subprocess.Popen([AUTOPOWER, "testbed", "up", "paper-fig7", "--json", "--speed", "5",
                             "--log-dir", str(tmp_path / "logs"), *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        return _wait_started(proc, tmp_path, env)
    except BaseException:
        stop(proc)
        raise


def _wait_started(proc, tmp_path, env):
    def session_files():  # each team's files live in a directory of their own
        return list((tmp_path / "state" / "teams").glob("*/session.json"))

    wait_until(lambda: session_files() or proc.poll() is not None, 60, "the testbed's session file")
    assert proc.poll() is None, proc.stderr.read()[-2000:]
    session_file = session_files()[0]

    def ready():
        if proc.poll() is not None:
            raise AssertionError(f"testbed up exited early: {proc.stderr.read()[-2000:]}")
        status = run_cli(["status", "--json", "--timeout", "2"], env)
        return status.returncode == 0 and json.loads(status.stdout).get("ready")

    wait_until(ready, 90, "the testbed team to be ready")
    return proc, json.loads(session_file.read_text()), env


def test_testbed_runs_the_team_in_namespaces_and_a_silent_cut_is_detected(tmp_path, clean):
    proc, session, env = start_testbed(tmp_path, "--lease-ms", "500")  # what `up` uses
    run_id = session["testbed"]
    try:
        mine = {n for n in ours() if n.startswith(f"{PREFIX}{run_id}-")}
        # one per node, and one for the bridge of the radio all four share (802.11a)
        assert mine == {f"{PREFIX}{run_id}-{n}" for n in ("laptop", "r1", "r2", "r3", "medium1")}
        # each process really is in its node's namespace
        for node, pid in session["children"].items():
            if node == "operator-bridge":
                continue
            ns = subprocess.run(["ip", "netns", "identify", str(pid)], capture_output=True, text=True).stdout.strip()
            assert ns == f"{PREFIX}{run_id}-{node}", (node, ns)
        snap = json.loads(run_cli(["status", "--json"], env).stdout)
        before = len(snap["faults"])
        # the table `status` draws (and `up` keeps live) has each chain's end-to-end latency
        # (each chain once it has an output: `status` answers in 0.3 s, before Loc-1's first at x5)
        def chain_rows():
            table = run_cli(["status"], {**env, "COLUMNS": "200"}).stdout
            assert "chains (end-to-end latency, source to sink)" in table
            rows = {line.split("│")[1].strip(): line for line in table.splitlines() if line.count("│") == 8}
            return rows if {"Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3"} <= set(rows) else None
        rows = wait_until(chain_rows, 15, "every chain's row in the status table")
        assert " ms" in rows["Blob-2"], rows
        result = run_cli(["fault", "cut", "r1", "laptop", "--json"], env)
        assert result.returncode == 0, result.stderr
        t_cut = json.loads(result.stdout)["fault"]["t_unix"]

        def handled():
            s = json.loads(run_cli(["status", "--json", "--timeout", "3"], env).stdout)
            # only what followed our cut (a loaded machine can make a short lease expire on its own)
            return next((f for f in s["faults"][before:] if f["kind"] == "link-down" and f["target"] == "laptop-r1"
                         and f["detected_unix"] >= t_cut and f["reconfigured_unix"]), None)

        fault = wait_until(handled, 20, "the cut to be detected and handled")
        print(f"testbed cut: detected {fault['detected_unix'] - t_cut:.3f} s, "
              f"reconfigured {fault['reconfigured_unix'] - t_cut:.3f} s")
        assert fault["detected_unix"] - t_cut <= 1.0
        assert fault["reconfigured_unix"] - t_cut <= 1.5
        assert json.loads(run_cli(["status", "--json"], env).stdout)["robots"]["r1"]["present"]  # via a relay
        assert run_cli(["fault", "heal", "r1", "laptop"], env).returncode == 0
        wait_until(lambda: not json.loads(run_cli(["status", "--json"], env).stdout)["links_down"], 20,
                   "the link back")
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-2000:]
        summary = json.loads(out)
        assert summary["shaped"] and summary["links"]["r1-laptop"] == {"medium": "802.11a", "kbit_s": 54000 * 5,
                                                                       "shared": True}
        assert summary["shared_media"] == {"802.11a": {"nodes": ["r1", "r2", "r3", "laptop"],
                                                       "kbit_s_per_node": 54000 * 5}}
    finally:
        stop(proc)  # after a failed assertion too, so it cleans up
    assert not {n for n in ours() if n.startswith(f"{PREFIX}{run_id}-")}, "Ctrl-C left namespaces behind"


def test_testbed_down_cleans_a_killed_run_and_nothing_else(tmp_path, clean):
    foreign = f"{PREFIX}notmine{os.getpid()}"  # our prefix, but no run recorded it
    subprocess.run(["ip", "netns", "add", foreign], check=True)
    session: dict = {}
    try:
        proc, session, env = start_testbed(tmp_path)
        run_id = session["testbed"]
        os.killpg(os.getpgid(proc.pid), signal.SIGKILL) if os.getpgid(proc.pid) == proc.pid else proc.kill()
        proc.wait()
        left = {n for n in ours() if n.startswith(f"{PREFIX}{run_id}-")}
        assert left, "a SIGKILLed run cannot clean up; the namespaces should still be there"
        result = run_cli(["testbed", "down", "--json"], env)
        assert result.returncode == 0, result.stderr
        assert set(json.loads(result.stdout)["removed"]) == left
        assert not {n for n in ours() if n.startswith(f"{PREFIX}{run_id}-")}
        assert foreign in list_namespaces(), "testbed down removed a namespace it did not create"
    finally:
        subprocess.run(["ip", "netns", "del", foreign], check=False)
        for pid in (session.get("children") or {}).values():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_without_root_it_is_one_line_and_exit_2(tmp_path, root):
    # a user namespace without a mapping: the same files, but not root any more
    for args in (["testbed", "up"], ["testbed", "down"]):
        result = subprocess.run(["unshare", "--user", AUTOPOWER, *args], env=env_for(tmp_path),
                                capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, result.stderr
        assert result.stderr.startswith("error: the testbed needs root") and result.stderr.count("\n") == 1
