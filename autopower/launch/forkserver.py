"""`up`'s side of its fork server (`autopower.cli.forkserver`): start it, ask it for processes,
and hold each as the part of `subprocess.Popen` that `up` uses.

A team process spends about half a second of CPU importing Zenoh, NumPy, HiGHS and the runtime
before it does anything. `up` starts the whole team at once: 31 processes importing together on
a 2-core machine held the base station's start back by seconds, and a 30-robot fleet's ready
time with it. Forked from one process that has imported everything once, each starts at once.
The rules a forked process follows to be as good as a fresh one are the server's
(`autopower.cli.forkserver`).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

from autopower.runtime.pids import pid_exists

READY_TIMEOUT_S = 30.0
SERVER_MODULE = "autopower.cli.forkserver"


# ---- `up`'s side -----------------------------------------------------------------------------------
class ForkedProcess:
    """A process the fork server started: the part of `subprocess.Popen` that `up` uses."""

    def __init__(self, pid: int, args: list[str]):
        self.pid = pid
        self.args = args  # the command that would start the same process from its starter (`Popen.args`)
        self.returncode: int | None = None
        self._ended = threading.Event()
        self._orphan = False  # its server is gone: no one will report its end

    def _exited(self, status: int) -> None:
        self.returncode = status
        self._ended.set()

    def _orphaned(self) -> None:
        self._orphan = True
        self._ended.set()  # wake a waiter: it looks for itself

    def poll(self) -> int | None:
        if self.returncode is None and self._orphan and not pid_exists(self.pid):  # a zombie has not ended yet (not `pid_alive`)
            self.returncode = -signal.SIGTERM  # what its server's death sent it; its own status is lost
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout)
            self._ended.wait(0.05 if self._orphan else left)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


class ForkServer:
    """`up`'s handle on its fork server: start it, ask it for processes, learn how they ended."""

    def __init__(self, env: dict[str, str]):
        self._proc = subprocess.Popen([sys.executable, "-m", SERVER_MODULE], env=env,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None,
                                      text=True, start_new_session=False)
        self._lock = threading.Lock()
        self._replies: list[dict] = []
        self._reply_ready = threading.Condition(self._lock)
        self._children: dict[int, ForkedProcess] = {}
        self._ended_early: dict[int, int] = {}  # pid -> status, reported before its spawn returned
        self.pid: int | None = None
        ready = self._proc.stdout.readline()  # its imports: the first process waits for them anyway
        try:
            self.pid = int(json.loads(ready)["ready"])
        except (ValueError, KeyError, TypeError):
            self.close()
            raise OSError(f"the fork server did not start (said {ready!r})") from None
        self._reader = threading.Thread(target=self._read, name="forkserver", daemon=True)
        self._reader.start()

    def spawn(self, argv: list[str], log_path: str, args: list[str] | None = None, nice: int = 0,
              netns: str | None = None) -> ForkedProcess:
        """Fork a process running ``autopower.cli.processes`` with ``argv``; ``args``: the command
        that would start it as a new interpreter, kept as its `ForkedProcess.args`; ``nice``: added
        to its nice value before it starts anything; ``netns``: the network namespace it joins
        before it opens a socket (the testbed's nodes)."""
        request = {"argv": argv, "log": log_path, "nice": nice, **({"netns": netns} if netns else {})}
        with self._lock:
            self._proc.stdin.write(json.dumps(request) + "\n")
            self._proc.stdin.flush()
            while not self._replies:
                if not self._reply_ready.wait(READY_TIMEOUT_S) or self._proc.poll() is not None:
                    raise OSError("the fork server stopped answering")
            reply = self._replies.pop(0)
            if "pid" not in reply:
                raise OSError(reply.get("error", f"unexpected reply {reply!r}"))
            child = self._children[reply["pid"]] = ForkedProcess(reply["pid"], args or argv)
            if reply["pid"] in self._ended_early:
                child._exited(self._ended_early.pop(reply["pid"]))
            return child

    @property
    def alive(self) -> bool:
        return self._proc.poll() is None

    def _read(self) -> None:
        for line in self._proc.stdout:
            try:
                message = json.loads(line)
            except ValueError:
                continue
            with self._lock:
                if "exit" in message:
                    child = self._children.get(message["exit"])
                    if child is None:
                        self._ended_early[message["exit"]] = message["status"]
                    else:
                        child._exited(message["status"])
                else:
                    self._replies.append(message)
                    self._reply_ready.notify_all()
        with self._lock:  # the server is gone (its children got SIGTERM): they end unreported
            for child in self._children.values():
                if child.returncode is None:
                    child._orphaned()
            self._reply_ready.notify_all()

    def close(self) -> None:
        """No more processes to start; the server reports the rest and ends after the last."""
        try:
            self._proc.stdin.close()
        except OSError:
            pass
