"""Stage worker processes: each hosted stage's component in a process of its own, called asynchronously.

Why: a node's loop is one Python thread. The base station hosts all five stages of the paper's
optimum; run on its loop they need one interpreter's worth of CPU and more from about x55 on
(docs/performance.md). With stage workers (``--stage-workers``) the loop hands a stage its next
input and goes on; the result comes back as an event and the loop emits it as it always did
(same sequence numbers, custody, acknowledgements, metering). A worker runs one input at a time
in the order it was given them (up to `WINDOW` ahead: it never waits for the loop between runs),
which keeps each stage's order; different stages run on different cores. An input handed to a
worker is acknowledged to its producer only once its output has gone out (`outstanding`, used by
`Acknowledging.acknowledged`), and a node whose worker has `WINDOW` + `STAGE_QUEUE` inputs refuses the
next one before its gate takes it (`room`): either way the producer keeps it in custody.

How: a *zygote* (`stage_worker.py`) is started once per node with an explicit environment (no
secrets: the node's keys stay in the node) and a socketpair; it imports the components once and
forks one worker per stage instance, handing back the worker's end of a fresh socketpair (no
socket in the filesystem). A thread per worker only reads its results and nudges the node's
event queue (``notify``); everything else happens on the loop's thread.

Failures: a call that raises is the stage's failure (as in-process); a worker that dies is too
("crashed"); a call that hangs (the same rule as `guard.py`: past its limit and blocked, or still
computing after `guard.SPIN_FACTOR` limits) gets its worker SIGKILLed: nothing is left running. The
next instance of the stage gets a fresh worker.
"""

from __future__ import annotations

import logging
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from typing import Any, Callable

import msgpack

import autopower.node.guard as guard
from autopower.node.guard import ComponentHung
from autopower.node.stage_worker import receive, send
from autopower.runtime.memory import MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES

log = logging.getLogger("autopower.node.runtime")

WINDOW = 4  # inputs handed to a stage's worker ahead of its results (4 camera frames fit its socket buffer)
STAGE_QUEUE = 64  # inputs waiting behind the window; more are refused before the gate ("stage-queue-full")
ZYGOTE_START_S = 60.0  # wall seconds a zygote may take to import the components (a loaded machine)
# wall seconds a worker may take to build its component: the first build imports the component's
# module in the worker (seconds on a loaded machine); a constructor in-process has no limit at all
BUILD_LIMIT_S = 60.0
_IDLE_CPU_S = 0.001
# what a worker may see of the node's environment: enough to find Python and its packages
_ENV_KEEP = ("PATH", "LANG", "LC_ALL", "LC_CTYPE", "TMPDIR", "HOME", "VIRTUAL_ENV", "TZ")
_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# glibc's malloc kept giving a worker's large temporaries (a blob finder's 0.6 MB label arrays)
# back to the kernel after each run and faulting them in again on the next: 184 page faults and
# 0.45 ms of system time a run, 1.3 ms of CPU against 0.8 ms in-process. Kept in the process
# instead: a worker holds on to its peak use (a few MB for the built-in components). The team
# processes set the same thresholds with mallopt (`runtime.memory`); a zygote gets them through its
# environment, so that they hold from its first allocation on and in every worker it forks.
_MALLOC = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES)}


class WorkerCrashed(Exception):
    """The worker process ended in the middle of a call."""


def worker_environment() -> dict[str, str]:
    """The explicit environment of a zygote: no inherited secrets, the node's import path."""
    env = {k: os.environ[k] for k in _ENV_KEEP if k in os.environ}
    env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)  # the modules the node can import
    env.update({k: "1" for k in _THREADS})  # one core per worker: parallelism comes from the workers
    env.update(_MALLOC)
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def recipe_for(factory: Callable, kind: str, robot: str, seed: int, parameters: dict | None) -> list | None:
    """How a worker builds this component (`stage_worker.build`); None: it cannot (run in-process)."""
    from autopower import chains

    if factory is chains.make_component:
        spec = chains.get_component_type(kind)  # an unknown type fails here, as in-process
        origin = getattr(spec, "origin", None)
        if origin is not None:
            path = _importable(origin[0])
            return None if path is None or parameters else ["class", path, robot, seed]
        if getattr(spec.make_component, "__module__", "").startswith("autopower."):
            return ["registry", kind, robot, seed, parameters]
        return None  # registered at run time by other code: the worker would not know it
    path = _importable(factory)
    return None if path is None else ["call", path, kind, robot, seed, parameters]


def _importable(obj: Any) -> str | None:
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if not module or not qualname or "<" in qualname or module == "__main__":
        return None
    return f"{module}:{qualname}"


class Zygote:
    """The node's worker factory process (started by `prestart` or on first use; closed with the node)."""

    def __init__(self) -> None:
        self._sock: socket.socket | None = None
        self._proc: subprocess.Popen | None = None
        self._ready = False  # its "ready" received: it has imported what every worker needs
        self._lock = threading.Lock()

    def prestart(self) -> None:
        """Start the factory process now, without waiting for it: the first stage a node hosts
        must not wait on the node's loop for its imports (0.6 s at load 5 on this machine,
        seconds under load, in the middle of a subgroup commit). Called from the thread that
        will own it (it dies with the thread that started it, `_die_with_parent`). A start that
        fails is left to `fork` to report."""
        with self._lock:
            if self._proc is None:
                try:
                    self._spawn()
                except OSError:
                    self._stop()

    def fork(self) -> tuple[socket.socket, int]:
        with self._lock:
            if self._proc is None or self._proc.poll() is not None:
                self._stop()
                self._spawn()
            if not self._ready:
                self._await_ready()
            send(self._sock, ["fork"])
            data, fds, _, _ = socket.recv_fds(self._sock, 4096, 1)
            if not data or not fds:
                self._stop()
                raise WorkerCrashed("the stage worker zygote ended")
            _, pid = msgpack.unpackb(data)
            return socket.socket(fileno=fds[0]), int(pid)

    def _spawn(self) -> None:
        mine, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-c", "from autopower.node.stage_worker import main; main()", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), env=worker_environment(), stdin=subprocess.DEVNULL,
                stdout=2,  # a component's prints go to the node's log, never to a command's stdout
                start_new_session=False)
        finally:
            theirs.close()
        self._sock, self._ready = mine, False

    def _await_ready(self) -> None:
        mine = self._sock
        mine.settimeout(ZYGOTE_START_S)
        try:
            ready = receive(mine)
        except OSError:
            ready = None
        mine.settimeout(None)
        if not ready or ready[0] != "ready":
            self._stop()
            raise WorkerCrashed("the stage worker zygote did not start")
        self._ready = True

    def _stop(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            self._proc = None

    def close(self) -> None:
        with self._lock:
            self._stop()


class StageWorker:
    """One stage instance's worker process: synchronous calls (build, export, import) and
    asynchronous runs (`submit`; results via `poll` after ``notify``)."""

    def __init__(self, zygote: Zygote, notify: Callable[[], None] | None):
        self.sock, self.pid = zygote.fork()
        self._notify = notify
        self._responses: queue.SimpleQueue = queue.SimpleQueue()  # (reply or None, when it arrived)
        self.sent: deque = deque()  # (input, when sent): handed to the worker, no result yet, in order
        self.waiting: deque = deque()  # (input, payload) behind a full window
        self._last_reply_t = 0.0  # when the worker last finished a run (the next one starts then)
        self._probe: tuple[float, float] | None = None  # (when, CPU seconds) past the limit
        self.killed = False
        self._reader = threading.Thread(target=self._read, daemon=True, name=f"autopower-stage-worker-{self.pid}")
        self._reader.start()

    # ---- the reader thread: results only, then a nudge ---------------------------------------------
    def _read(self) -> None:
        while True:
            try:
                msg = receive(self.sock)
            except (OSError, ValueError, msgpack.UnpackException):
                msg = None
            self._responses.put((msg if isinstance(msg, list) and msg else None, time.monotonic()))
            if self._notify is not None:
                self._notify()
            if msg is None:
                return

    # ---- synchronous calls (the loop waits, with the hang rule) ------------------------------------
    def call(self, op: str, *args: Any, timeout_s: float, wall_limit: bool = False) -> list:
        """The reply to ``op`` (["ok", ...], ["bad", type] or ["err", type, text]).

        Raises `ComponentHung` (the worker is killed) or `WorkerCrashed`. The hang rule is
        `guard.py`'s, or with ``wall_limit`` ``timeout_s`` of wall time alone."""
        if self.sent or self.waiting:
            raise RuntimeError("a synchronous call while runs are outstanding")
        try:
            self._send([op, *args])
        except OSError as exc:
            raise WorkerCrashed(f"the worker process ended before {op} ({self.exit_text()})") from exc
        started = time.monotonic()
        self._probe = None
        while True:
            try:
                reply, _ = self._responses.get(timeout=min(guard.BLOCKED_PROBE_S, timeout_s))
            except queue.Empty:
                waited = time.monotonic() - started
                verdict = (f"no result after {waited:.3g} s (limit {timeout_s:.3g} s)" if waited >= timeout_s else None
                           ) if wall_limit else self.hung(started, timeout_s, time.monotonic())
                if verdict is not None:
                    self.kill()
                    raise ComponentHung(verdict) from None
                continue
            if reply is None:
                raise WorkerCrashed(f"the worker process ended during {op} ({self.exit_text()})")
            return reply

    # ---- asynchronous runs -------------------------------------------------------------------------
    @property
    def inflight(self) -> tuple[Any, float] | None:
        """(the input the worker runs now, since when); None when it has nothing to do."""
        if not self.sent:
            return None
        item, sent_t = self.sent[0]
        return item, max(sent_t, self._last_reply_t)

    def room(self) -> int:
        """How many more inputs it takes (`WINDOW` handed over + `STAGE_QUEUE` waiting, at most).

        The node asks before its stage's gate takes an input (`Frames.admit`): an input it
        refuses stays in its producer's custody and is resent, where one dropped after the gate
        would be lost (the gate counts it consumed)."""
        return WINDOW + STAGE_QUEUE - len(self.sent) - len(self.waiting)

    def outstanding(self):
        """Every input handed over whose result the loop has not taken yet, oldest first."""
        for item, _ in self.sent:
            yield item
        for item, _ in self.waiting:
            yield item

    def submit(self, item: Any, payload: bytes) -> None:
        """Hand over an input (the caller has checked `room`).

        Up to `WINDOW` inputs go to the worker at once (its socket is a FIFO: it runs them one at a
        time, in order), so it never waits for the loop to collect a result before its next run."""
        if len(self.sent) < WINDOW and not self.waiting:
            self._send_run(item, payload)
        else:
            self.waiting.append((item, payload))

    def poll(self, timeout_s: float = 0.0) -> tuple[Any, list | None] | None:
        """(the input, its reply) of the oldest run once it has finished (reply None: the worker
        died); None while it runs (waiting up to ``timeout_s``). Waiting inputs fill the window."""
        if not self.sent:
            return None
        try:
            reply, at = self._responses.get(timeout=timeout_s) if timeout_s > 0 else self._responses.get_nowait()
        except queue.Empty:
            return None
        item, _ = self.sent.popleft()
        self._last_reply_t = at
        self._probe = None
        if reply is None:  # the process ended: nothing else handed to it will come back
            self.sent.clear()
            self.waiting.clear()
        while reply is not None and self.waiting and len(self.sent) < WINDOW:
            self._send_run(*self.waiting.popleft())
        return item, reply

    def hung(self, started: float, limit_s: float, now: float) -> str | None:
        """Why the call that started at ``started`` has hung, or None (guard.py's rule)."""
        waited = now - started
        if waited < limit_s:
            return None
        cpu = self.cpu_s()
        if waited >= guard.SPIN_FACTOR * limit_s:
            return f"no result after {waited:.3g} s (still running; limit {limit_s:.3g} s)"
        if cpu is None:
            return f"no result after {waited:.3g} s (limit {limit_s:.3g} s)"
        if self._probe is None:
            self._probe = (now, cpu)
        elif now - self._probe[0] >= guard.BLOCKED_PROBE_S:
            if cpu - self._probe[1] < _IDLE_CPU_S:
                return f"no result after {waited:.3g} s (blocked; limit {limit_s:.3g} s)"
            self._probe = (now, cpu)
        return None

    def run_hung(self, limit_s: float, now: float) -> str | None:
        return None if self.inflight is None else self.hung(self.inflight[1], limit_s, now)

    def _send_run(self, item: Any, payload: bytes) -> None:
        self.sent.append((item, time.monotonic()))
        try:
            self._send(["run", payload])
        except OSError:
            pass  # it died: the reader reports the end of stream

    def _send(self, msg: list) -> None:
        send(self.sock, msg)

    # ---- the process -------------------------------------------------------------------------------
    def cpu_s(self) -> float | None:
        """CPU seconds the worker has used; None if unknown. From the scheduler's nanosecond count
        (`/proc/PID/schedstat`): clock ticks (10 ms) cannot tell a starved spinner from a blocked
        call over a short probe."""
        try:
            with open(f"/proc/{self.pid}/schedstat", "rb") as f:
                return int(f.read().split()[0]) / 1e9
        except (OSError, IndexError, ValueError):
            pass
        try:
            with open(f"/proc/{self.pid}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, IndexError, ValueError):
            return None

    def exit_text(self) -> str:
        return "killed" if self.killed else "it exited or was killed"

    def kill(self) -> None:
        """SIGKILL the worker (a hung call, or the stage is done here); its socket closes."""
        if not self.killed:
            self.killed = True
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.sent.clear()
        self.waiting.clear()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class WorkerComponent:
    """A component living in a `StageWorker`, with the in-process component's interface.

    ``run``, ``export_state`` and ``import_state`` called on it are synchronous calls (the
    node's loop dispatches runs asynchronously through ``worker`` instead). ``export_state`` and
    ``import_state`` exist only when the component has them."""

    def __init__(self, worker: StageWorker, recipe: list, timeout_s: float):
        self.worker = worker
        caps = self._ok(worker.call("build", recipe, timeout_s=BUILD_LIMIT_S, wall_limit=True), "constructor")
        self.timeout_s = timeout_s
        if caps.get("export"):
            self.export_state = self._export
        if caps.get("import"):
            self.import_state = self._import

    def run(self, payload: bytes) -> bytes:
        return self._ok(self.worker.call("run", payload, timeout_s=self.timeout_s), "run")  # its output is last

    def _export(self) -> bytes:
        return self._ok(self.worker.call("export", timeout_s=self.timeout_s), "export_state")

    def _import(self, state: bytes) -> None:
        self._ok(self.worker.call("import", state, timeout_s=self.timeout_s), "import_state")

    @staticmethod
    def _ok(reply: list, what: str):
        if reply[0] == "ok":
            return reply[-1]  # the constructor's capabilities, a run's output, a state
        if reply[0] == "bad":
            return NotBytes(reply[1])  # the caller checks isinstance(..., bytes), as in-process
        raise remote_error(str(reply[1]), str(reply[2]) if len(reply) > 2 else "")

    def close(self) -> None:
        self.worker.kill()


class NotBytes:
    """What a worker's component returned instead of bytes (only its type name crosses)."""

    def __init__(self, type_name: str):
        self.type_name = str(type_name)


class RemoteError(Exception):
    """An exception a component raised in its worker (only its type's name and text cross)."""


_REMOTE_TYPES: dict[str, type] = {}


def remote_error(type_name: str, text: str) -> RemoteError:
    """A `RemoteError` whose class has the remote exception's name (messages say ``KeyError: ...``
    for a component in a worker as for one in-process)."""
    name = type_name if type_name.isidentifier() else "Exception"
    cls = _REMOTE_TYPES.get(name)
    if cls is None:
        cls = _REMOTE_TYPES[name] = type(name, (RemoteError,), {"__module__": __name__})
    return cls(text)


def type_name(value: Any) -> str:
    return value.type_name if isinstance(value, NotBytes) else type(value).__name__


def worker_of(component: Any) -> StageWorker | None:
    """The worker a hosted component (or the component a fan-in join wraps) runs in, if any."""
    inner = getattr(component, "inner", component)
    return inner.worker if isinstance(inner, WorkerComponent) else None
