"""Fault injection into a running team: `autopower fault cut|loss|rate|flap|roam|heal|kill|crash|freeze|thaw|radio`.

`loss` (random packet loss) and `cut --one-way` act on one direction of a link, `rate` re-shapes
a link, `flap` cuts and brings back a link again and again, `roam` cuts it once for a moment:
only the testbed can do them (its links are real interfaces; see `autopower.launch.netns`), so a
team on loopback proxies refuses them rather than pretend.

A flap or a roam is a `_Schedule`: the controller cuts the link at once and a thread of its own
brings it back (and, for a flap, cuts it again) on time. The thread changes the link only under
the controller's lock and after checking it was not stopped, so once `heal`, the end of
``--for`` or `close` (the team stops) has stopped it and restored the link, the link stays up.

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
from dataclasses import dataclass, field
from itertools import cycle
from pathlib import Path

from autopower.errors import AutoPowerError

log = logging.getLogger(__name__)

SOCKET_NAME = "control.sock"
MEDIA_CHOICES = ("802.11a", "gsm", "bluetooth")
# a flap's phases (s): at least two tc calls' time, at most an hour; a roam's outage (ms): a
# fast 802.11r roam takes 50-150 ms, a full re-association seconds
PHASE_S = (0.05, 3600.0)
ROAM_MS = (1.0, 60000.0)
# what each testbed-only link fault is called when a localhost team refuses it
TESTBED_ONLY = {"loss": "packet loss", "cut": "a one-way cut", "rate": "a rate change", "flap": "a flapping link",
                "roam": "a roaming outage"}


@dataclass
class _Schedule:
    """A flap or a roam in progress on one link: the thread that keeps it and how to stop it."""

    kind: str
    label: str  # what `fault list` shows, e.g. "flap 1s up 2s down"
    proxy: object
    target: str
    entry: dict  # its line in the controller's log: gets ``ended_unix`` when it ends
    stop: threading.Event = field(default_factory=threading.Event)
    thread: threading.Thread | None = None


class FaultController:
    """Carries out faults on a `LocalTeam` (thread-safe; used by the control server and the demo)."""

    def __init__(self, team):
        self.team = team
        self.log: list[dict] = []
        self._lock = threading.Lock()
        self._mission: dict | None = None
        self._schedules: dict[frozenset[str], _Schedule] = {}  # link -> its flap or roam

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
            t, t_mono = time.time(), time.monotonic()
            details: dict = {}
            healed: list[str] = []
            if op == "loss" or (op == "cut" and request.get("one_way")):
                target, details = self._drop(op, request)
            elif op == "rate":
                target, details = self._rate(request)
            elif op in ("flap", "roam"):
                target, details = self._schedule(op, request, t_mono)
            elif op in ("cut", "heal"):
                a, b = request.get("a"), request.get("b")
                proxy = self.team.proxy(a, b)
                schedule = self._schedules.get(frozenset((a, b)))
                if op == "cut" and schedule is not None:  # its next up phase would undo this cut
                    raise AutoPowerError(f"link {a}-{b} has a {schedule.kind} running ({schedule.label}); "
                                         f"`autopower fault heal {a} {b}` ends it, then cut")
                if op == "heal":  # each kind in place is recorded as healed (nothing in place: a cut, as ever)
                    healed = self._stop_schedule(a, b, t) + _impairments(proxy, scheduled=schedule is not None)
                    healed = healed or ["cut"]
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
                return {"ok": True, "faults": [dict(f) for f in self.log], "supervision": self.team.supervision(),
                        "links": {"-".join(sorted(p)): self._link_label(p, x) for p, x in self.team.proxies.items()}}
            else:
                raise AutoPowerError(f"unknown fault operation {op!r}")
            entry = details.pop("entry", {})  # a schedule's entry is its own, to be marked when it ends
            entry.update({"kind": op, "target": target, "t_unix": t, **details})
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
        proxy = self._testbed_link(op, a, b)
        pct = 100.0 if op == "cut" else request.get("pct")
        directions = [(a, b)] if one_way else [(a, b), (b, a)]
        for src, dst in directions:
            proxy.drop(src, dst, pct, kind=op)
        towards = f"{a}->{b}" if one_way else "both ways"
        what = f"{a}->{b} only" if op == "cut" else f"{float(pct):g}% of packets {towards}"
        return f"{a}-{b}", {"direction": towards, "pct": float(pct), "what": what}

    def _testbed_link(self, op: str, a, b):
        """The testbed link a-b, or a clear error on a localhost team (its proxies only cut both ways)."""
        proxy = self.team.proxy(a, b)
        if not hasattr(proxy, "drop"):
            raise AutoPowerError(f"{TESTBED_ONLY[op]} needs the testbed (`sudo autopower testbed up`): this team's "
                                 "links are loopback TCP proxies, which can only cut a link both ways "
                                 f"(`autopower fault cut {a} {b}`)")
        return proxy

    def _rate(self, request: dict) -> tuple[str, dict]:
        """`fault rate A B KBPS`: the link shaped to KBPS (× the team's speed-up), both ways."""
        from autopower.launch.netns import rate_kbps

        a, b = request.get("a"), request.get("b")
        proxy = self._testbed_link("rate", a, b)
        kbps = rate_kbps(request.get("kbps"))
        proxy.set_rate(kbps)
        return f"{a}-{b}", {"kbps": kbps, "what": f"{kbps:g} kbit/s both ways"}

    def _schedule(self, op: str, request: dict, started: float) -> tuple[str, dict]:
        """`fault flap` / `fault roam`: cut the link now; a thread of its own brings it back on time.

        Its phases are timed from `started` (monotonic), the instant the fault's `t_unix` was taken,
        not from when the first cut's tc calls returned: on a loaded machine they took 0.3 s, and
        every later switch came that much after the time the fault's record gives for it.
        """
        a, b = request.get("a"), request.get("b")
        proxy = self._testbed_link(op, a, b)
        key, target = frozenset((a, b)), f"{a}-{b}"
        running = self._schedules.get(key)
        if running is not None:
            raise AutoPowerError(f"link {target} already has a {running.kind} running ({running.label}); "
                                 f"`autopower fault heal {a} {b}` ends it first")
        if proxy.is_cut:  # the schedule's up phase would undo a cut someone else made
            raise AutoPowerError(f"link {target} is cut; `autopower fault heal {a} {b}` first")
        if op == "flap":
            up_s = _bounded(request.get("up_s"), PHASE_S, "--up", "seconds")
            down_s = _bounded(request.get("down_s"), PHASE_S, "--down", "seconds")
            for_s = request.get("for_s")
            if for_s is not None:
                for_s = _bounded(for_s, (PHASE_S[0], float("inf")), "--for", "seconds")
            steps = cycle([(down_s, "up"), (up_s, "down")])
            label = f"flap {up_s:g}s up {down_s:g}s down"
            details = {"up_s": up_s, "down_s": down_s, "what": f"{down_s:g} s down, {up_s:g} s up"
                       + (f", for {for_s:g} s" if for_s is not None else ", until healed")}
            if for_s is not None:
                details["for_s"] = for_s
        else:
            ms = _bounded(request.get("ms"), ROAM_MS, "MS", "milliseconds")
            for_s, steps = None, [(ms / 1000, "end")]
            label, details = f"roam {ms:g} ms", {"ms": ms, "what": f"a {ms:g} ms outage"}
        schedule = _Schedule(kind=op, label=label, proxy=proxy, target=target, entry={})
        proxy.cut()  # the first down phase starts now, at the fault's time
        until = None if for_s is None else started + for_s
        schedule.thread = threading.Thread(target=self._keep, args=(key, schedule, steps, started, until),
                                           name=f"{op}-{target}", daemon=True)
        self._schedules[key] = schedule
        schedule.thread.start()
        return target, {**details, "entry": schedule.entry}

    def _keep(self, key: frozenset, schedule: _Schedule, steps, started: float, until: float | None) -> None:
        """The schedule's thread: after each step's seconds, bring the link up, cut it, or end (up)."""
        at = started
        for seconds, then in steps:
            at += seconds  # from the start, not from each wake-up: no drift over a long flap
            if until is not None and until <= at:
                at, then = until, "end"
            if schedule.stop.wait(max(0.0, at - time.monotonic())):
                return  # stopped: whoever stopped it has brought the link back
            with self._lock:
                if schedule.stop.is_set():
                    return
                try:
                    schedule.proxy.cut() if then == "down" else schedule.proxy.uncut()
                except Exception as exc:  # noqa: BLE001 - e.g. the namespaces are gone: end, logged
                    log.warning("%s %s: %s; the %s ends", schedule.kind, schedule.target, exc, schedule.kind)
                    then = "end"
                if then == "end":
                    self._end(key, time.time())
                    return

    def _end(self, key: frozenset, t: float) -> None:
        """The schedule on ``key`` is over (by itself, --for, heal or close): mark it, record it healed."""
        schedule = self._schedules.pop(key)
        schedule.stop.set()
        schedule.entry["ended_unix"] = t
        self._record(schedule.kind, "healed", schedule.target, t)

    def _stop_schedule(self, a: str, b: str, t: float) -> list[str]:
        """Stop the flap or roam on a-b (under the lock; `heal` then restores the link); its kind, or []."""
        schedule = self._schedules.get(frozenset((a, b)))
        if schedule is None:
            return []
        schedule.stop.set()
        schedule.entry["ended_unix"] = t
        del self._schedules[frozenset((a, b))]
        return [schedule.kind]

    def _link_label(self, key: frozenset, proxy) -> str:
        schedule = self._schedules.get(key)
        state = _link_state(proxy)
        return state if schedule is None else f"{schedule.label}, now {state}"

    def close(self) -> None:
        """Stop every flap and roam and bring their links up (the team stops: nothing is left cut)."""
        with self._lock:
            schedules = list(self._schedules.items())
            for key, schedule in schedules:
                schedule.stop.set()
                try:
                    schedule.proxy.uncut()
                except Exception as exc:  # noqa: BLE001 - the others must still be stopped
                    log.warning("%s %s not brought back: %s", schedule.kind, schedule.target, exc)
                self._end(key, time.time())
        for _key, schedule in schedules:
            schedule.thread.join(timeout=5.0)

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


def _impairments(proxy, scheduled: bool = False) -> list[str]:
    """The kinds of fault in place on a link (``cut``, ``loss``, ``rate``), in a stable order.

    ``scheduled``: a flap or roam runs on it, so a both-way cut is its down phase, not a `cut`.
    """
    kinds = {"cut"} if proxy.is_cut and not scheduled else set()
    kinds |= {d.kind for d in getattr(proxy, "drops", {}).values()}
    if getattr(proxy, "rate", None) is not None:
        kinds.add("rate")
    return sorted(kinds)


def _bounded(value, bounds: tuple[float, float], name: str, unit: str) -> float:
    """``value`` as a number within ``bounds``; a clear error naming the option otherwise."""
    low, high = bounds
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (low <= number <= high):
        give = f"between {low:g} and {high:g}" if high < float("inf") else f"at least {low:g}"
        raise AutoPowerError(f"{name} {value!r} is out of range: give {give} {unit}")
    return number


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
        """Stop serving, then stop the controller's flaps and roams (the team is about to stop)."""
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
        stop_schedules = getattr(self.controller, "close", None)  # any object with `apply` may be served
        if stop_schedules is not None:
            stop_schedules()


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

