"""`up`'s fork server: children forked after one import behave as the fresh interpreters they
replace (exit statuses, logs, signals, process groups) and end with it."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

from autopower.launch.forkserver import ForkServer
from autopower.launch.localhost import child_environment


@pytest.fixture
def server():
    srv = ForkServer(child_environment(dict(os.environ)))
    yield srv
    for child in list(srv._children.values()):
        child.kill()
    srv.close()
    srv._proc.wait(timeout=10)


def test_a_forked_child_exits_with_its_status_and_writes_its_log(server, tmp_path):
    log = tmp_path / "r1.log"
    ok = server.spawn(["agent", "--help"], str(log))
    assert ok.wait(timeout=30) == 0
    assert "--robot" in log.read_text()  # its stdout went to its log
    bad = server.spawn(["agent", "--no-such-option"], str(log))
    assert bad.wait(timeout=30) == 2  # a usage error, as the CLI exits with it
    assert "No such option" in log.read_text()  # stderr too, appended


def test_a_forked_child_has_its_own_group_hears_signals_and_its_end_is_reported(server, tmp_path):
    child = server.spawn(["agent", "--robot", "r1", "--scenario", "paper-fig7", "--team", "forktest",
                          "--parent-pid", str(server.pid)], str(tmp_path / "r1.log"))
    assert os.getpgid(child.pid) == child.pid  # its own process group (faults signal the group)
    time.sleep(1.0)
    # its command line is the server's: `ps` and `top` tell it by the name it gave itself
    assert Path(f"/proc/{child.pid}/comm").read_text().strip() == "ap-r1"
    assert child.poll() is None  # its parent is the server it names: it runs
    child.send_signal(signal.SIGTERM)
    assert child.wait(timeout=30) == 0  # a clean stop on SIGTERM, as under `up`
    killed = server.spawn(["agent", "--robot", "r2", "--scenario", "paper-fig7", "--team", "forktest",
                           "--parent-pid", str(server.pid)], str(tmp_path / "r2.log"))
    killed.kill()
    assert killed.wait(timeout=30) == -signal.SIGKILL
    running = server.spawn(["agent", "--robot", "r3", "--scenario", "paper-fig7", "--team", "forktest",
                            "--parent-pid", str(server.pid)], str(tmp_path / "r3.log"))
    with pytest.raises(subprocess.TimeoutExpired):
        running.wait(timeout=0.5)
    running.terminate()
    assert running.wait(timeout=30) == 0


def test_children_die_with_the_server(tmp_path):
    srv = ForkServer(child_environment(dict(os.environ)))
    child = srv.spawn(["agent", "--robot", "r1", "--scenario", "paper-fig7", "--team", "forktest2",
                       "--parent-pid", str(srv.pid)], str(tmp_path / "r1.log"))
    time.sleep(0.5)
    srv._proc.kill()  # the server killed: its children get SIGTERM (PR_SET_PDEATHSIG) and stop
    srv._proc.wait(timeout=10)
    assert child.wait(timeout=30) is not None
    with pytest.raises(ProcessLookupError):
        os.kill(child.pid, 0)


def nice_of_every_thread(pid: int) -> set[int]:
    """The nice value of each of a process's threads (field 19 of /proc/<pid>/task/<tid>/stat)."""
    tasks = Path(f"/proc/{pid}/task")
    return {int((tasks / tid / "stat").read_text().rsplit(")", 1)[1].split()[16]) for tid in os.listdir(tasks)}


def test_a_child_asked_to_be_nicer_is_so_in_every_thread_it_starts(server, tmp_path):
    """`up --robot-nice`: the agent's nice value is raised before it starts a thread, so Zenoh's
    threads and the loop's all run at it (a thread keeps the value of the thread that made it)."""
    own = os.nice(0)
    plain = server.spawn(["agent", "--robot", "r1", "--scenario", "paper-fig7", "--team", "nicetest",
                          "--parent-pid", str(server.pid)], str(tmp_path / "r1.log"))
    nicer = server.spawn(["agent", "--robot", "r2", "--scenario", "paper-fig7", "--team", "nicetest",
                          "--parent-pid", str(server.pid)], str(tmp_path / "r2.log"), nice=5)
    time.sleep(1.5)  # its Zenoh session is open: its threads are running
    try:
        assert len(os.listdir(f"/proc/{nicer.pid}/task")) > 1
        assert nice_of_every_thread(nicer.pid) == {min(19, own + 5)}
        assert nice_of_every_thread(plain.pid) == {own}
    finally:
        for child in (plain, nicer):
            child.terminate()
    assert plain.wait(timeout=30) == 0 and nicer.wait(timeout=30) == 0


def test_a_child_started_as_a_new_interpreter_is_as_nice_as_asked():
    """Without the fork server (`TeamSpec.fork_server=False`, or when it fails) the child is made
    nicer between fork and exec, as the fork server does."""
    import functools
    import sys

    from autopower.launch.localhost import _prepare_child

    own = os.nice(0)
    out = subprocess.run([sys.executable, "-c", "import os; print(os.nice(0))"], capture_output=True, text=True,
                         preexec_fn=functools.partial(_prepare_child, 3), timeout=30, check=True)
    assert int(out.stdout) == min(19, own + 3)


def _netns_inode(path: str) -> int:
    return os.stat(path).st_ino


def test_a_child_asked_into_a_network_namespace_runs_there_with_every_thread(server, tmp_path):
    """The testbed forks its nodes from the fork server: each joins its node's namespace before it
    opens a socket, as `ip netns exec` would put it there. Needs root (CI runs as root)."""
    if os.geteuid() != 0:
        pytest.skip("creating a network namespace needs root")
    name = f"apfork{os.getpid()}"
    subprocess.run(["ip", "netns", "add", name], check=True)
    try:
        inside = server.spawn(["agent", "--robot", "r1", "--scenario", "paper-fig7", "--team", "nstest",
                               "--parent-pid", str(server.pid)], str(tmp_path / "r1.log"), netns=name)
        time.sleep(1.5)  # its Zenoh session is open: its threads are running
        try:
            threads = os.listdir(f"/proc/{inside.pid}/task")
            assert len(threads) > 1
            assert {_netns_inode(f"/proc/{inside.pid}/task/{t}/ns/net") for t in threads} \
                == {_netns_inode(f"/var/run/netns/{name}")}
            assert _netns_inode(f"/proc/{server.pid}/ns/net") == _netns_inode("/proc/self/ns/net")  # not the server
        finally:
            inside.terminate()
        assert inside.wait(timeout=30) == 0
        # a namespace that does not exist: the child says so in its log and exits 1, nothing else starts
        log = tmp_path / "r2.log"
        missing = server.spawn(["agent", "--robot", "r2", "--scenario", "paper-fig7", "--team", "nstest",
                                "--parent-pid", str(server.pid)], str(log), netns=f"{name}-gone")
        assert missing.wait(timeout=30) == 1
        assert f"{name}-gone" in log.read_text() and "joined team" not in log.read_text()
    finally:
        subprocess.run(["ip", "netns", "del", name], check=False)
