"""Per-team state: each team's session file and control socket in a directory of its own.

Two teams on one machine must not take over each other's `status` and `fault`; a team that
exits removes only its own files; the files of a team whose `up` died are recognised and
removed; the control socket is private whatever the umask, and checks who is calling.
"""

from __future__ import annotations

import json
import os
import socket
import stat
import subprocess
import sys
import time

import pytest

from autopower.basestation.operator import (
    clear_session,
    read_session,
    running_sessions,
    team_dir,
    write_session,
)
from autopower.errors import AutoPowerError
from autopower.launch.faults import SOCKET_NAME, FaultServer, request_fault


@pytest.fixture
def state(tmp_path, monkeypatch):
    monkeypatch.setenv("AUTOPOWER_STATE_DIR", str(tmp_path / "state"))
    return tmp_path / "state"


@pytest.fixture
def other_process():
    """A live process that is not this one (another team's `up`)."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc.pid
    proc.kill()
    proc.wait()


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_commands_pick_the_only_team_or_ask_which(state, other_process):
    with pytest.raises(AutoPowerError, match="no running team found"):
        read_session()
    write_session({"team": "alpha", "pid": os.getpid(), "connect": ["tcp/127.0.0.1:1"]})
    assert read_session()["team"] == "alpha"  # the only one: no --team needed
    write_session({"team": "beta", "pid": other_process, "connect": ["tcp/127.0.0.1:2"]})
    with pytest.raises(AutoPowerError, match=r"2 teams are running \(alpha, beta\); choose one with --team"):
        read_session()
    assert read_session("beta")["connect"] == ["tcp/127.0.0.1:2"]
    with pytest.raises(AutoPowerError, match="no running team 'gamma'.*running: alpha, beta"):
        read_session("gamma")


def test_a_team_that_exits_removes_only_its_own_files(state, other_process):
    write_session({"team": "alpha", "pid": os.getpid()})
    write_session({"team": "beta", "pid": other_process})
    (team_dir("beta") / SOCKET_NAME).write_text("")  # beta's control socket
    clear_session("beta")  # not ours: beta's `up` is another process
    assert (state / "teams" / "beta" / "session.json").exists()
    clear_session("alpha")
    assert not (state / "teams" / "alpha").exists()
    assert set(running_sessions()) == {"beta"} and (state / "teams" / "beta" / SOCKET_NAME).exists()


def test_files_of_a_dead_team_are_recognised_and_removed(state):
    write_session({"team": "ghost", "pid": _dead_pid()})
    (team_dir("ghost") / SOCKET_NAME).write_text("")
    keys = state / "tls" / "ghost"  # what `up` made for it (autopower.launch.identities)
    keys.mkdir(parents=True)
    (keys / "r1.key").write_text("")
    (state / "teams" / "broken").mkdir()
    (state / "teams" / "broken" / "session.json").write_text("{not json")
    assert running_sessions() == {}
    assert not (state / "teams" / "ghost").exists() and not (state / "teams" / "broken").exists()
    assert not keys.exists()
    with pytest.raises(AutoPowerError, match="no running team found"):
        read_session()


def test_state_is_private_whatever_the_umask(state):
    previous = os.umask(0)
    try:
        session = write_session({"team": "alpha", "pid": os.getpid()})
        server = FaultServer(_Echo(), team_dir("alpha") / SOCKET_NAME)
    finally:
        os.umask(previous)
    with server:
        assert stat.S_IMODE(session.stat().st_mode) == 0o600
        assert stat.S_IMODE(session.parent.stat().st_mode) == 0o700
        assert stat.S_IMODE(state.stat().st_mode) == 0o700
        assert stat.S_IMODE(server.path.stat().st_mode) == 0o600
        write_session({"team": "alpha", "pid": os.getpid(), "control": str(server.path)})
        assert request_fault({"op": "list"}, team="alpha") == {"ok": True, "echo": {"op": "list"}}
    assert not server.path.exists()


def test_the_control_socket_sleeps_until_a_request_and_closes_at_once(state):
    """No wake-up every 0.1 s to look for a shutdown flag (socketserver's serve_forever): `up` at rest."""
    write_session({"team": "alpha", "pid": os.getpid()})
    server = FaultServer(_Echo(), team_dir("alpha") / SOCKET_NAME).__enter__()
    try:
        write_session({"team": "alpha", "pid": os.getpid(), "control": str(server.path)})
        assert request_fault({"op": "list"}, team="alpha")["ok"]
        task = f"/proc/self/task/{server._thread.native_id}/status"
        switches = lambda: int(open(task).read().split("voluntary_ctxt_switches:")[1].split()[0])  # noqa: E731
        before = switches()
        time.sleep(1.0)
        assert switches() - before <= 1  # asleep the whole second (was ~10 wake-ups)
        assert request_fault({"op": "list"}, team="alpha") == {"ok": True, "echo": {"op": "list"}}
    finally:
        started = time.monotonic()
        server.close()
    assert time.monotonic() - started < 1.0 and not server._thread.is_alive() and not server.path.exists()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to act as another user")
def test_the_control_socket_refuses_another_user(monkeypatch):
    import shutil
    import tempfile

    base = tempfile.mkdtemp(prefix="ap-peercred-", dir="/tmp")  # pytest's own tmp dir is closed to others
    os.chmod(base, 0o755)
    state = os.path.join(base, "state")
    monkeypatch.setenv("AUTOPOWER_STATE_DIR", state)
    try:
        _refuses_another_user(state)
    finally:
        shutil.rmtree(base)


def _refuses_another_user(state):
    write_session({"team": "alpha", "pid": os.getpid()})
    with FaultServer(_Echo(), team_dir("alpha") / SOCKET_NAME) as server:
        # open the modes so that only the uid check stands between another user and the team
        os.chmod(state, 0o755)
        os.chmod(server.path.parent.parent, 0o755)
        os.chmod(server.path.parent, 0o755)
        os.chmod(server.path, 0o666)
        code = ("import os, socket, sys; os.setgid(65534); os.setuid(65534); "
                "s = socket.socket(socket.AF_UNIX); s.connect(sys.argv[1]); "
                "s.sendall(b'{\"op\": \"list\"}\\n'); print(s.recv(4096).decode())")
        out = subprocess.run([sys.executable, "-c", code, str(server.path)], capture_output=True, text=True,
                             timeout=20)
        assert out.returncode == 0, out.stderr
        reply = json.loads(out.stdout)
        assert reply == {"ok": False, "message": "refused: this team belongs to another user"}
        with socket.socket(socket.AF_UNIX) as sock:  # the owner is still served
            sock.connect(str(server.path))
            sock.sendall(b'{"op": "list"}\n')
            assert json.loads(sock.recv(4096).decode())["ok"]


class _Echo:
    """Stands in for the fault controller: the tests here are about who reaches it."""

    def apply(self, request: dict) -> dict:
        return {"ok": True, "echo": request}
