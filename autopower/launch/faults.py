"""Fault injection into a running team: `autopower fault cut|loss|heal|kill|crash|freeze|thaw|radio`.

`loss` (random packet loss) and `cut --one-way` act on one direction of a link: only the testbed
can do that (its links are real interfaces; see `autopower.launch.netns`), so a team on loopback
proxies refuses them rather than pretend.

`kill` takes a robot out for good (the supervisor lets it go); `crash` is a SIGKILL the
supervisor answers like any crash: it starts the process again (a robot's agent or the base
station).

The `up` supervisor owns the team's link proxies and child processes, so faults are carried
out there. It serves a small local control channel — a Unix socket in the team's own state
directory (0600 in a 0700 directory; the server also checks the caller's uid), one JSON
request per connection, one JSON reply — which works whatever the Zenoh links are doing (a
cut link must not cut the operator off from un-cutting it). The team's `session.json` says
where the socket is.

Every fault is recorded with its wall time (``t_unix``), so detection and reconfiguration can
be measured against the base station's own record of when it noticed (its snapshot's
``faults``).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import socketserver
import struct
import threading
import time
from pathlib import Path

from autopower.errors import AutoPowerError

log = logging.getLogger(__name__)

SOCKET_NAME = "control.sock"
MEDIA_CHOICES = ("802.11a", "gsm", "bluetooth")


class FaultController:
    """Carries out faults on a `LocalTeam` (thread-safe; used by the control server and the demo)."""

    def __init__(self, team):
        self.team = team
        self.log: list[dict] = []
        self._lock = threading.Lock()
        self._mission: dict | None = None

    def _robot(self, name: str) -> None:
        robots = [r.name for r in self.team.scenario.robots]
        if name not in robots:
            raise AutoPowerError(f"unknown robot {name!r}; robots of this team: {', '.join(robots)}")

    def _child(self, name: str, base_too: bool = False):
        if not (base_too and name == self.team.scenario.basestation):
            self._robot(name)
        child = self.team.children.get(name)
        if child is None or child.proc.poll() is not None:
            raise AutoPowerError(f"{name} is not running (already killed?)")
        return child

    def apply(self, request: dict) -> dict:
        op = request.get("op")
        with self._lock:
            t = time.time()
            details: dict = {}
            healed: list[str] = []
            if op == "loss" or (op == "cut" and request.get("one_way")):
                target, details = self._drop(op, request)
            elif op in ("cut", "heal"):
                a, b = request.get("a"), request.get("b")
                proxy = self.team.proxy(a, b)
                if op == "heal":  # each kind in place is recorded as healed (nothing in place: a cut, as ever)
                    healed = _impairments(proxy) or ["cut"]
                proxy.cut() if op == "cut" else proxy.heal()
                target = f"{a}-{b}"
            elif op in ("kill", "crash", "freeze", "thaw"):
                name = request.get("robot")
                child = self._child(name, base_too=op == "crash")
                sig = {"kill": signal.SIGKILL, "crash": signal.SIGKILL, "freeze": signal.SIGSTOP,
                       "thaw": signal.SIGCONT}[op]
                if op == "kill":
                    self.team.expected_exits.add(name)
                t = time.time()
                os.killpg(child.proc.pid, sig) if _own_group(child.proc.pid) else child.proc.send_signal(sig)
                target = name
                if op == "crash":  # the kinds the demo reports: which part of the team crashed
                    op = "crash-basestation" if name == self.team.scenario.basestation else "crash-agent"
            elif op == "radio":
                from autopower.protocol import LinkCommand

                name = request.get("robot")
                self._robot(name)
                laptop, robot = request.get("laptop"), request.get("robot_medium")
                for medium in (laptop, robot):
                    if medium is not None and medium not in MEDIA_CHOICES:
                        raise AutoPowerError(f"unknown medium {medium!r}; media: {', '.join(MEDIA_CHOICES)}")
                if laptop is None and robot is None:
                    raise AutoPowerError("radio: give --laptop and/or --robot")
                t = time.time()
                reply = self.team.client.request(LinkCommand(node=name, laptop_robot=laptop, robot_robot=robot), 5.0)
                if not reply.ok:
                    raise AutoPowerError(f"the base station refused: {reply.message}")
                target = name
            elif op == "list":
                return {"ok": True, "faults": list(self.log), "supervision": self.team.supervision(),
                        "links": {"-".join(sorted(p)): _link_state(x) for p, x in self.team.proxies.items()}}
            else:
                raise AutoPowerError(f"unknown fault operation {op!r}")
            entry = {"kind": op, "target": target, "t_unix": t, **details}
            self.log.append(entry)
            reason = details.get("what", "")
            if op == "heal":
                for kind in healed:
                    self._record(kind, "healed", target, t)
            else:
                kind, phase = ("freeze", "healed") if op == "thaw" else (op, "injected")
                self._record(kind, phase, target, t, reason=reason)
            log.info("fault: %s %s %s", op, target, reason)
            said = f"{op} {target}" + (f" ({reason})" if reason else "")
            return {"ok": True, "fault": entry, "message": f"{said} at {time.strftime('%H:%M:%S', time.localtime(t))}"}

    def _drop(self, op: str, request: dict) -> tuple[str, dict]:
        """Random loss (`loss`) or a one-way cut on a testbed link; (target, what the log keeps)."""
        a, b, one_way = request.get("a"), request.get("b"), bool(request.get("one_way"))
        proxy = self.team.proxy(a, b)
        if not hasattr(proxy, "drop"):
            what = "packet loss" if op == "loss" else "a one-way cut"
            raise AutoPowerError(f"{what} needs the testbed (`sudo autopower testbed up`): this team's links are "
                                 "loopback TCP proxies, which can only cut a link both ways "
                                 f"(`autopower fault cut {a} {b}`)")
        pct = 100.0 if op == "cut" else request.get("pct")
        directions = [(a, b)] if one_way else [(a, b), (b, a)]
        for src, dst in directions:
            proxy.drop(src, dst, pct, kind=op)
        towards = f"{a}->{b}" if one_way else "both ways"
        what = f"{a}->{b} only" if op == "cut" else f"{float(pct):g}% of packets {towards}"
        return f"{a}-{b}", {"direction": towards, "pct": float(pct), "what": what}

    def _record(self, kind: str, phase: str, target: str, t: float, reason: str = "") -> None:
        """Put the fault into the run's recording (when the team records), for replay."""
        run_dir = getattr(self.team.spec, "record_dir", None)
        if run_dir is None:
            return
        try:
            from autopower.recording.recorder import record_fault_event

            if self._mission is None:
                self._mission = self.team.snapshot(timeout_s=2.0).get("mission")
            record_fault_event(run_dir, kind=kind, target=target, phase=phase, reason=reason,
                               mission=self._mission, wall_unix=t)
        except Exception as exc:  # noqa: BLE001 - a recording problem must not stop the fault
            log.warning("fault %s %s %s not recorded: %s", kind, phase, target, exc)


def _link_state(proxy) -> str:
    """What `fault list` shows for a link: the testbed says what each direction drops."""
    state = getattr(proxy, "state", None)
    return state if isinstance(state, str) else ("cut" if proxy.is_cut else "up")


def _impairments(proxy) -> list[str]:
    """The kinds of fault in place on a link (``cut``, ``loss``), in a stable order."""
    kinds = {"cut"} if proxy.is_cut else set()
    kinds |= {d.kind for d in getattr(proxy, "drops", {}).values()}
    return sorted(kinds)


def _own_group(pid: int) -> bool:
    try:
        return os.getpgid(pid) == pid
    except OSError:
        return False


def peer_uid(sock: socket.socket) -> int:
    """The user id of the process at the other end of a Unix socket (SO_PEERCRED: from the kernel)."""
    creds = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    _pid, uid, _gid = struct.unpack("3i", creds)
    return uid


class FaultServer:
    """The supervisor's side of the control channel (a context manager)."""

    def __init__(self, controller: FaultController, path: Path):
        self.controller = controller
        self.path = Path(path)
        self._own_dir = False
        if len(str(self.path)) > 100:  # AF_UNIX paths are limited to ~108 bytes
            import tempfile

            self.path = Path(tempfile.mkdtemp(prefix="autopower-")) / SOCKET_NAME  # 0700, ours to remove
            self._own_dir = True
        self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(self.path.parent, 0o700)  # whatever the umask: only this user may reach the socket
        if self.path.exists():
            self.path.unlink()
        controller_ = controller

        class Handler(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                try:
                    uid = peer_uid(self.request)
                    if uid != os.getuid():  # the modes keep others out; this is the second lock
                        log.warning("control request from uid %s refused (this team belongs to uid %s)",
                                    uid, os.getuid())
                        reply = {"ok": False, "message": "refused: this team belongs to another user"}
                        # take its request first (bounded, not acted on): closing on an unread request
                        # broke the caller's send (EPIPE) before it could read why it was refused
                        self.request.settimeout(2.0)
                        try:
                            self.rfile.readline(65536)
                        except OSError:
                            pass
                        self.wfile.write((json.dumps(reply) + "\n").encode())
                        return
                    request = json.loads(self.rfile.readline().decode() or "{}")
                    reply = controller_.apply(request)
                except AutoPowerError as exc:
                    reply = {"ok": False, "message": str(exc)}
                except Exception as exc:  # a bad request must not take the supervisor down
                    log.exception("fault request failed")
                    reply = {"ok": False, "message": f"internal error: {exc}"}
                self.wfile.write((json.dumps(reply) + "\n").encode())

        previous = os.umask(0o177)  # the socket is born 0600: no window in which others may connect
        try:
            self._server = socketserver.ThreadingUnixStreamServer(str(self.path), Handler)
        finally:
            os.umask(previous)
        os.chmod(self.path, 0o600)
        self._server.daemon_threads = True
        # it sleeps in `select` until a request or `close` (a pipe) wakes it: socketserver's
        # serve_forever looks for its shutdown flag every poll_interval (10 wake-ups a second at 0.1)
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = False
        self._thread = threading.Thread(target=self._serve, name="fault-server", daemon=True)

    def _serve(self) -> None:
        import selectors

        with selectors.DefaultSelector() as selector:
            selector.register(self._server, selectors.EVENT_READ)
            selector.register(self._wake_r, selectors.EVENT_READ)
            while not self._stopping:
                ready = selector.select()
                if not self._stopping and any(key.fileobj is self._server for key, _ in ready):
                    self._server.handle_request()  # one connection, ready: accept does not wait

    def __enter__(self) -> "FaultServer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._stopping:
            return
        self._stopping = True
        os.write(self._wake_w, b"x")
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        os.close(self._wake_r)
        os.close(self._wake_w)
        self._server.server_close()
        try:
            self.path.unlink()
        except FileNotFoundError:
            pass
        if self._own_dir:
            try:
                self.path.parent.rmdir()
            except OSError:
                pass


def request_fault(request: dict, timeout_s: float = 10.0, team: str | None = None) -> dict:
    """Send one request to a running team's supervisor (`team`, default the only one; its session file)."""
    from autopower.basestation.operator import read_session

    session = read_session(team, remote_hint=False)  # faults are injected by the `up` on this machine only
    path = session.get("control")
    if not path:
        raise AutoPowerError("the running team was started without a fault control channel; "
                             "restart it with `autopower up`")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.connect(path)
        except OSError as exc:
            raise AutoPowerError(f"cannot reach the team's supervisor at {path} ({exc}); "
                                 "is `autopower up` still running?") from None
        sock.sendall((json.dumps(request) + "\n").encode())
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    try:
        reply = json.loads(data.decode())
    except json.JSONDecodeError:
        raise AutoPowerError(f"the supervisor at {path} gave no answer") from None
    if not reply.get("ok"):
        raise AutoPowerError(reply.get("message", "fault failed"))
    return reply

