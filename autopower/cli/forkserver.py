"""`up`'s fork server: one process imports what a team process needs, then forks each of them
(`up`'s side: `autopower.launch.forkserver`). Its pages are shared copy-on-write; each child does
only its own work.

Rules that make a forked process as good as a fresh one:
- the server opens no Zenoh session and starts no thread (a forked child keeps only the thread
  that forked; a session's runtime does not survive a fork): it is single-threaded, and waits
  on its requests and a wake-up pipe for SIGCHLD with `select`;
- each child gets what `subprocess.Popen` gave it: its own process group, SIGTERM when its
  parent (this server) dies, stdin from /dev/null, stdout and stderr appended to its log, and the
  signal dispositions a fresh interpreter sets up; it runs the process entry point (`autopower.cli.processes`) with its
  arguments, its exit handlers, and exits with its status;
- the server reaps its children and reports each exit status; it dies with `up` (SIGTERM).

Protocol, one JSON object per line. `up` -> server (stdin): ``{"argv": [...], "log": path, "nice": n,
"netns": name}`` (``nice``, optional: added to the child's nice value before it starts anything;
``netns``, optional: the network namespace, made by ``ip netns add``, the child joins before it
opens a socket: the testbed's nodes).
Server -> `up` (stdout): ``{"ready": pid}`` once its imports are done, ``{"pid": n}`` for each
request in order (``{"error": why}`` if the fork failed), ``{"exit": pid, "status": code}``
(a signal as a negative code, as `subprocess` has it).
"""

from __future__ import annotations

import gc
import json
import os
import select
import signal
import sys
from typing import IO

# what every team process imports before its first message (the rest is cheap)
PRELOAD = ("zenoh", "numpy", "networkx", "msgpack", "highspy", "autopower.cli.processes", "autopower.agent.process",
           "autopower.basestation.process", "autopower.recording.recorder")


# ---- the server ---------------------------------------------------------------------------------------
def serve() -> None:
    """The server's loop (``python -m autopower.cli.forkserver``)."""
    import importlib

    _die_with_parent()
    for name in PRELOAD:
        try:
            importlib.import_module(name)
        except ImportError:  # optional for some processes: the child imports (or fails) as before
            pass
    # what the imports made is never garbage: out of the collector's sight, a child's full
    # collections walk its own objects only (56 ms fewer per collection on this machine, a pause
    # in every loop that made it), and do not write to the pages it shares with the server
    gc.collect()
    gc.freeze()
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so the wake-up fd is written
    out = sys.stdout
    _say(out, {"ready": os.getpid()})
    stdin = sys.stdin.buffer
    pending = b""
    while True:
        readable, _, _ = select.select([stdin, wake_r], [], [])
        if wake_r in readable:
            os.read(wake_r, 4096)
        _reap(out)
        if stdin in readable:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:  # `up` closed our stdin: it is done starting processes
                break
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                _fork(out, json.loads(line), (wake_r, wake_w))
    # the children go on (their own groups); report their ends until the last is gone
    while True:
        try:
            pid, status = os.waitpid(-1, 0)
        except ChildProcessError:
            return
        _say(out, {"exit": pid, "status": os.waitstatus_to_exitcode(status)})


def _reap(out: IO[str]) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        _say(out, {"exit": pid, "status": os.waitstatus_to_exitcode(status)})


def _fork(out: IO[str], request: dict, own_fds: tuple[int, int]) -> None:
    try:
        log_fd = os.open(request["log"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    except OSError as exc:
        _say(out, {"error": f"cannot open {request['log']}: {exc}"})
        return
    try:
        pid = os.fork()
    except OSError as exc:
        os.close(log_fd)
        _say(out, {"error": f"fork failed: {exc}"})
        return
    if pid:
        os.close(log_fd)
        try:
            os.setpgid(pid, pid)  # as the child does: its group exists before anyone signals it
        except OSError:  # it did it first (EACCES once it runs its program), or it is gone
            pass
        _say(out, {"pid": pid})
        return
    _child(request["argv"], log_fd, own_fds, int(request.get("nice", 0)), request.get("netns"))  # never returns


def _child(argv: list[str], log_fd: int, own_fds: tuple[int, int], nice: int = 0, netns: str | None = None) -> None:
    code = 1
    try:
        if nice > 0:  # first: a thread keeps the nice value of the thread that created it
            os.nice(nice)
        signal.set_wakeup_fd(-1)
        for fd in own_fds:
            os.close(fd)
        # the dispositions a fresh interpreter starts with: SIGPIPE and SIGXFSZ ignored (a write to
        # a closed socket raises instead of killing: a child thawed after its links timed out was
        # killed by SIGPIPE while it kept the server's defaults), SIGINT raising KeyboardInterrupt
        for sig in (signal.SIGCHLD, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        for sig in (signal.SIGPIPE, signal.SIGXFSZ):
            signal.signal(sig, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        os.setpgid(0, 0)
        _die_with_parent()
        _name_process(argv)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(log_fd, 1)
        os.dup2(log_fd, 2)
        for fd in (null, log_fd):
            os.close(fd)
        sys.stdin = open(0, closefd=False)  # noqa: SIM115 - the process's own stdin, as Python opens it
        sys.stdout = open(1, "w", buffering=1, closefd=False)  # noqa: SIM115 - line-buffered, as -u gives
        sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115
        if netns is not None:  # after the log is ours (a refusal is written there), before any socket
            _enter_netns(netns)
        sys.argv = ["autopower.cli.processes", *argv]
        from autopower.cli.processes import main

        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        import atexit

        atexit._run_exitfuncs()  # what a fresh interpreter does on its way out
    except BaseException:  # noqa: BLE001 - nothing may return into the server's loop
        import traceback

        traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _say(out: IO[str], message: dict) -> None:
    out.write(json.dumps(message) + "\n")
    out.flush()


def _name_process(argv: list[str]) -> None:
    """Name the process after what it runs (``ap-r1``, ``ap-basestation``): a forked child's command
    line is still the server's, so `ps -o comm`, `top` and `pgrep` tell the team's processes apart by
    this name (at most 15 bytes, the kernel's limit)."""
    what = argv[argv.index("--robot") + 1] if "--robot" in argv[:-1] else (argv[0] if argv else "process")
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(15, f"ap-{what}".encode()[:15])  # PR_SET_NAME
    except Exception:  # noqa: BLE001 - not Linux: the name is only a convenience
        pass


NETNS_DIR = "/var/run/netns"  # where `ip netns add` keeps a handle on each namespace
CLONE_NEWNET = 0x40000000


def _enter_netns(name: str) -> None:
    """Join the network namespace ``name``, as `ip netns exec` does for the sockets a program opens.

    setns moves the calling thread only: the child is still single-threaded here, so the whole
    process is in the namespace, and every thread it starts later is too."""
    if not name or "/" in name or name in (".", ".."):
        raise ValueError(f"not a network namespace name: {name!r}")
    fd = os.open(os.path.join(NETNS_DIR, name), os.O_RDONLY | os.O_CLOEXEC)
    try:
        if hasattr(os, "setns"):  # Python 3.12+
            os.setns(fd, CLONE_NEWNET)
            return
        import ctypes

        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        if libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"cannot enter network namespace {name}: {os.strerror(err)}")
    finally:
        os.close(fd)


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - not Linux: the process checks its parent itself (--parent-pid)
        pass


if __name__ == "__main__":
    serve()
