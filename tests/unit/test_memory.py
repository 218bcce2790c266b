"""The team processes' allocator setting (`autopower.runtime.memory`)."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from autopower.runtime import memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_large_buffers_are_kept_on_glibc():
    # in a child: the setting is for the whole process and stays
    code = "from autopower.runtime.memory import keep_large_buffers as k; print(k())"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "True"


def test_without_mallopt_nothing_is_tuned(monkeypatch):
    class NoMallopt:
        def __init__(self, _name):
            pass

    monkeypatch.setattr(memory.ctypes, "CDLL", NoMallopt)
    assert memory.keep_large_buffers() is False


def test_the_team_processes_set_it_before_their_loop():
    import inspect

    from autopower.cli import processes

    source = inspect.getsource(processes.run_until_signalled)
    assert source.index("keep_large_buffers()") < source.index("process.run(")
