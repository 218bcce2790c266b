"""`pid_alive`: the one check of whether a process runs (session files, testbed runs, forked children)."""

from __future__ import annotations

import os
import subprocess
import sys

from autopower.runtime.pids import pid_alive


def test_a_running_process_is_alive_an_exited_one_is_not_even_unreaped():
    assert pid_alive(os.getpid())
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    os.waitid(os.P_PID, child.pid, os.WEXITED | os.WNOWAIT)  # exited, left a zombie (not reaped)
    assert not pid_alive(child.pid)
    child.wait()
    assert not pid_alive(child.pid)


def test_what_is_not_a_pid_is_not_alive():
    for bad in (None, "123", 0, -1, 1.5):
        assert not pid_alive(bad)
