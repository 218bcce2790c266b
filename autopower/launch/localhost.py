"""Start a whole team on this machine: the base station and one agent per robot, as processes.

Used by `autopower up` and by the integration tests. Everything listens and connects on
127.0.0.1 only, on ports picked free at start; scouting is off, so nothing leaves loopback
and parallel runs never meet. Every pair of nodes gets exactly one Zenoh connection (the
later node connects to the earlier one), and the endpoint used for each pair can be replaced
(``peer_endpoints``), e.g. by a forwarding proxy that can cut that one link.

Children are put in their own process group (a Ctrl-C reaches only `up`, which stops them in
order) and get SIGTERM if `up` itself dies (Linux PR_SET_PDEATHSIG; elsewhere they notice
their parent is gone at their next status tick).

The team is supervised like a service manager would (`autopower.launch.supervisor`): a child
that crashes is started again with the same command after a backoff while the others keep
running; one that crashes too often, or exits 2 (bad configuration), is given up and
reported. A thread of the launcher does the watching; `check_children` hands whoever drives the
team (`up`'s loop, the demo) the events since its last call.
"""

from __future__ import annotations

import functools
import json
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from autopower.basestation.operator import OperatorClient, private_dir
from autopower.errors import AutoPowerError
from autopower.launch.forkserver import ForkedProcess, ForkServer
from autopower.launch.supervisor import RestartPolicy, Supervisor, SupervisorEvent
from autopower.model.network import build_network
from autopower.model.scenario import Scenario
from autopower.runtime.bus import TRANSPORTS, ZenohSettings

log = logging.getLogger(__name__)

HOST = "127.0.0.1"
SUPERVISE_EVERY_S = 0.05  # how often the supervisor looks for crashed children (without pidfds)
READY_HOLD_S = 2.0  # `wait_ready`: how long one query waits for the team (then the children are looked at)
SUPERVISE_IDLE_S = 0.5  # with pidfds it sleeps until a child exits, a restart is due, or this long


def free_ports(n: int, host: str = HOST, kind: int = socket.SOCK_STREAM) -> list[int]:
    """Ports free right now on ``host`` (held open together so they are distinct); TCP ports, or UDP
    ones with ``kind=socket.SOCK_DGRAM`` (what a QUIC listener binds)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, kind)
            s.bind((host, 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def endpoint(port: int, host: str = HOST, scheme: str = "tcp") -> str:
    return f"{scheme}/{host}:{port}"


def pair_endpoints(nodes: list[str], ports: dict[str, int],
                   overrides: dict[tuple[str, str], str] | None = None, scheme: str = "tcp") -> dict[str, list[str]]:
    """For each node, the endpoints it connects to: one per earlier node (one link per pair).

    ``overrides[(node, peer)]`` replaces the endpoint ``node`` uses to reach ``peer`` (a proxy).
    """
    overrides = overrides or {}
    out: dict[str, list[str]] = {}
    for i, node in enumerate(nodes):
        out[node] = [overrides.get((node, peer), endpoint(ports[peer], scheme=scheme)) for peer in nodes[:i]]
    return out


def child_environment(base: dict[str, str]) -> dict[str, str]:
    """The environment of a team's processes: unbuffered logs, and compiled modules they can share.

    With PYTHONDONTWRITEBYTECODE set (nothing may be written beside the sources), every child
    would compile the same few hundred modules at each start: about 0.25 CPU s each, which a
    fleet of 30 processes on one 2-core machine pays 30 times over before anything runs. They
    read and write them instead in a cache of their own (0700), which
    keeps the source tree as clean as the variable asks; `precompile` fills it once. It is a cache,
    not the team's state: under the user's cache directory, shared by every team they start."""
    env = {**base, "PYTHONUNBUFFERED": "1"}
    if env.get("PYTHONDONTWRITEBYTECODE") and not env.get("PYTHONPYCACHEPREFIX"):
        del env["PYTHONDONTWRITEBYTECODE"]
        cache = Path(base.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "autopower" / "pycache"
        env["PYTHONPYCACHEPREFIX"] = str(private_dir(cache))
    return env


def precompile(env: dict[str, str]) -> None:
    """Compile the package into the children's private cache (`child_environment`) before they
    start, so that they do not all compile it at once; a no-op when the sources are unchanged."""
    if "PYTHONPYCACHEPREFIX" not in env or env.get("PYTHONDONTWRITEBYTECODE"):
        return
    package = Path(__file__).resolve().parents[1]
    try:
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(package)], env=env, timeout=120,
                       stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except (OSError, subprocess.SubprocessError) as exc:  # only slower: each child compiles what it needs
        log.warning("could not precompile %s for the team's processes: %s", package, exc)


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


def _prepare_child(nice: int) -> None:  # runs in the child between fork and exec
    _die_with_parent()
    if nice > 0:
        os.nice(nice)


PARENT_PID = "{parent}"  # in a child's arguments: the pid of the process that starts it (`_with_parent`)


def _with_parent(args: list[str], pid: int) -> list[str]:
    return [str(pid) if a == PARENT_PID else a for a in args]


@dataclass
class Child:
    name: str
    proc: subprocess.Popen | ForkedProcess
    log_path: Path

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""


@dataclass(kw_only=True)
class TeamSpec:
    scenario: str  # a built-in name or a path
    speed: float = 10.0
    energy: tuple[str, ...] = ()  # "r1=32000"
    energy_scale: float | None = None
    accounting: str | None = None
    topology: str | None = None
    media: tuple[str, ...] = ()  # "laptop-robot=gsm"
    pins: tuple[str, ...] = ()  # "Loc-2=r1"
    auto_replan: bool = True
    policy: str = "rebalance"  # the base station's --policy
    stage_workers: str = "off"  # every process's --stage-workers (off, on, auto)
    # added to every robot agent's nice value (not the base station's): on one machine the robots
    # share the cores a base station has to itself on a real team (`up --robot-nice`)
    robot_nice: int = 0
    lease_ms: int = 1000
    # Zenoh keep-alives per lease on an idle link: most of what a team at rest costs (each is
    # received by Zenoh and copied by a link proxy). Two on loopback, where nothing is lost and a
    # link still survives a quarter-second hiccup at a 0.5 s lease; the processes' own default
    # (4) stays for links that lose packets (a radio under TCP waits out a retransmission).
    keep_alive: int = 2
    status_period_s: float = 0.5
    heartbeat_s: float = 2.0  # a status with nothing new in it, this often (`runtime.cadence`)
    team: str | None = None
    log_dir: Path | None = None
    log_level: str = "info"
    extra_basestation_args: tuple[str, ...] = ()
    endpoint_overrides: dict[tuple[str, str], str] = field(default_factory=dict)
    # one LinkProxy per link of the scenario's topology (a fault can cut it silently); pairs
    # with no link get no connection at all, so relaying is done by the agents
    proxied_links: bool = False
    record_dir: Path | None = None  # every process writes its Rerun recording here (merge_run joins them)
    # mutual TLS and default-deny access control, as on real hosts (`autopower.launch.identities`);
    # False is `--insecure`: plain tcp, anyone who reaches a port controls the team
    secure: bool = True
    # what carries a secure team's links (`runtime.bus.TRANSPORTS`): "tls" (TCP) or "quic"
    transport: str = "tls"
    tls_dir: Path | None = None  # where the team's CA and identities go (default: under the state dir)
    restart: RestartPolicy | None = field(default_factory=RestartPolicy)  # None: a crash stops the team
    # the children forked from one process that imported their modules once (`launch.forkserver`);
    # False: each starts as a new interpreter
    fork_server: bool = True


def check_transport(spec: TeamSpec) -> None:
    """A transport the team can run, or one line saying why not."""
    if spec.transport not in TRANSPORTS:
        raise AutoPowerError(f"transport {spec.transport!r}: expected one of {', '.join(TRANSPORTS)}")
    if spec.transport != "tls" and not spec.secure:
        raise AutoPowerError(f"--insecure is plain tcp: it cannot run over {spec.transport}, which is always TLS; "
                             "drop --insecure or --transport")
    if spec.transport != "tls" and spec.proxied_links:
        raise AutoPowerError(f"a localhost team's link proxies forward TCP: its links cannot run over "
                             f"{spec.transport}; use the testbed (its links are real interfaces)")


class LocalTeam:
    """A team of processes on localhost (a context manager: leaving it stops every child)."""

    def __init__(self, spec: TeamSpec, scenario: Scenario):
        check_transport(spec)
        self.spec = spec
        self.scenario = scenario
        self.team = spec.team or f"up-{os.getpid()}-{secrets.token_hex(3)}"
        self.log_dir = Path(spec.log_dir) if spec.log_dir else Path(tempfile.mkdtemp(prefix="autopower-up-"))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.nodes = [scenario.basestation] + [r.name for r in scenario.robots]  # base first: it listens first
        self.identities = None
        if spec.secure:
            from autopower.launch.identities import LocalIdentities

            self.identities = LocalIdentities.create(self.team, self.nodes, spec.tls_dir)
        self.scheme = spec.transport if spec.secure else "tcp"
        ports = free_ports(len(self.nodes), kind=socket.SOCK_DGRAM if self.scheme == "quic" else socket.SOCK_STREAM)
        self.ports = dict(zip(self.nodes, ports, strict=True))
        self.proxies: dict[frozenset[str], "LinkProxy"] = {}
        if spec.proxied_links:
            from autopower.launch.linkproxy import LinkProxy

            topology = build_network(scenario, topology=spec.topology)
            pairs = {frozenset((l.a, l.b)) for l in topology.links}
            self.connects = {}
            for i, node in enumerate(self.nodes):
                self.connects[node] = []
                for peer in self.nodes[:i]:  # the later node connects to the earlier one
                    pair = frozenset((node, peer))
                    if pair not in pairs:
                        continue
                    taken = set(self.ports.values())
                    proxy = LinkProxy(f"{peer}-{node}", self.ports[peer])
                    for _ in range(20):  # port 0 may hand out a node's port (they were only reserved)
                        if proxy.port not in taken:
                            break
                        retry = LinkProxy(f"{peer}-{node}", self.ports[peer])
                        proxy.close()
                        proxy = retry
                    self.proxies[pair] = proxy
                    self.connects[node].append(endpoint(proxy.port, scheme=self.scheme))
        else:
            self.connects = pair_endpoints(self.nodes, self.ports, spec.endpoint_overrides, self.scheme)
        self.child_env = child_environment(dict(os.environ))
        self._forkserver: ForkServer | None = None  # started with the team (`start`)
        self.expected_exits: set[str] = set()  # children a fault killed on purpose
        self.children: dict[str, Child] = {}
        self._commands: dict[str, list[str]] = {}  # name -> the arguments it was started with
        self.supervisor = Supervisor(spec.restart) if spec.restart is not None else None
        self._down: set[str] = set()  # crashed children the supervisor has seen (until restarted)
        self._stopping = False
        self._lock = threading.RLock()  # the supervisor thread and the callers of check_children
        self._pending_events: list[SupervisorEvent] = []
        self._supervisor_thread: threading.Thread | None = None
        self._news = threading.Event()  # set when the supervisor thread has events for `check_children`
        self.mission: dict | None = None  # the base station's mission clock, for recording events
        self.client: OperatorClient | None = None
        self.exit_codes: dict[str, int | None] = {}

    @property
    def base_endpoint(self) -> str:
        return endpoint(self.ports[self.scenario.basestation], scheme=self.scheme)

    def _common(self, node: str) -> list[str]:
        args = ["--scenario", self.spec.scenario, "--team", self.team,
                "--listen", endpoint(self.ports[node], scheme=self.scheme), "--lease-ms", str(self.spec.lease_ms),
                "--keep-alive", str(self.spec.keep_alive),
                "--status-period", str(self.spec.status_period_s), "--heartbeat", str(self.spec.heartbeat_s),
                "--parent-pid", PARENT_PID, "--log-level", self.spec.log_level,
                "--stage-workers", self.spec.stage_workers]
        for ep in self.connects[node]:
            args += ["--connect", ep]
        if self.spec.record_dir is not None:
            args += ["--record-dir", str(self.spec.record_dir)]
        if self.identities is not None:
            args += ["--tls", str(self.identities.directory)]
        return args

    def _command(self, name: str, args: list[str]) -> list[str]:
        # the process entry points alone: a child does not import the rest of the CLI
        return [sys.executable, "-m", "autopower.cli.processes", *args]

    def _netns(self, name: str) -> str | None:
        """The network namespace a child runs in (None: this one; the testbed's nodes have their own)."""
        return None

    def _spawn(self, name: str, args: list[str]) -> None:
        """Start a child: forked from the fork server (its imports done once for all), or, without
        one, as a fresh interpreter. Its parent (whose end it follows: ``--parent-pid``) is the one
        that started it. A restarted child's log goes on after its crash."""
        log_path = self.log_dir / f"{name}.log"
        self._commands[name] = args
        nice = 0 if name == self.scenario.basestation else self.spec.robot_nice
        proc = None
        if self._forkserver is not None and self._forkserver.alive:
            try:
                proc = self._forkserver.spawn(_with_parent(args, self._forkserver.pid), str(log_path),
                                              args=self._command(name, _with_parent(args, os.getpid())), nice=nice,
                                              netns=self._netns(name))
            except OSError as exc:
                log.warning("fork server: %s; starting %s as a new interpreter", exc, name)
        if proc is None:
            with open(log_path, "ab") as out:
                proc = subprocess.Popen(self._command(name, _with_parent(args, os.getpid())), stdin=subprocess.DEVNULL,
                                        stdout=out, stderr=subprocess.STDOUT, process_group=0,
                                        preexec_fn=functools.partial(_prepare_child, nice), env=self.child_env)
        self.children[name] = Child(name, proc, log_path)

    def proxy(self, a: str, b: str):
        """The LinkProxy of the link a-b; AutoPowerError if there is none."""
        nodes = self.nodes
        for n in (a, b):
            if n not in nodes:
                raise AutoPowerError(f"unknown node {n!r}; nodes of this team: {', '.join(nodes)}")
        proxy = self.proxies.get(frozenset((a, b)))
        if proxy is None:
            links = ", ".join("-".join(sorted(p)) for p in self.proxies) or "none (started without link proxies)"
            raise AutoPowerError(f"no link {a}-{b} in this team's topology; links: {links}")
        return proxy

    def start(self) -> None:
        precompile(self.child_env)
        if self.spec.fork_server:
            try:
                self._forkserver = ForkServer(self.child_env)
            except OSError as exc:  # only slower: every child imports for itself
                log.warning("no fork server (%s); each process starts as a new interpreter", exc)
        for proxy in self.proxies.values():
            proxy.start()
        spec, base = self.spec, self.scenario.basestation
        args = ["basestation", *self._common(base), "--speed", str(spec.speed)]
        for item in spec.energy:
            args += ["--energy", item]
        if spec.energy_scale is not None:
            args += ["--energy-scale", str(spec.energy_scale)]
        if spec.accounting:
            args += ["--accounting", spec.accounting]
        if spec.topology:
            args += ["--topology", spec.topology]
        for item in spec.media:
            args += ["--media", item]
        for pin in spec.pins:
            args += ["--pin", pin]
        if not spec.auto_replan:
            args.append("--no-replan")
        args += ["--policy", spec.policy]
        args += list(spec.extra_basestation_args)
        self._spawn(base, args)
        for robot in self.nodes[1:]:
            self._spawn(robot, ["agent", "--robot", robot, *self._common(robot)])
        if self.supervisor is not None:
            self._supervisor_thread = threading.Thread(target=self._supervise, name="supervisor", daemon=True)
            self._supervisor_thread.start()
        # `up`'s own session watches no radio and carries no frames (a snapshot every few seconds):
        # the team's keep-alives, and no shared memory (whose watchdog threads wake 30 times a second)
        own = self.operator_settings() or ZenohSettings(connect=(self.base_endpoint,))
        self.client = OperatorClient(self.team, connect=(self.base_endpoint,),
                                     settings=replace(own, keep_alive=self.spec.keep_alive, shared_memory=False))

    def session_security(self) -> dict:
        """What session.json needs for `autopower status` etc. to join as the operator (paths only)."""
        if self.identities is None:
            return {"insecure": True}
        files = self.identities.files("operator")
        return {"operator_tls": {"ca": files.ca, "cert": files.cert, "key": files.key}}

    def operator_settings(self):
        """How an operator reaches this team's base station (None: a plain session to base_endpoint)."""
        if self.identities is None:
            return None
        return self.identities.operator_settings(self.base_endpoint)

    def check_children(self) -> list[SupervisorEvent]:
        """The supervisor's events since the last call (a crash restarts that child; the rest run on).

        The supervising itself runs in its own thread (`_supervise`), so restarts do not wait for
        a caller busy with a base station that does not answer. Without a restart policy
        (``TeamSpec.restart=None``) a crash raises here instead.
        """
        events = self._supervise_once()
        with self._lock:
            events = self._pending_events + events
            self._pending_events = []
        return events

    def exited_cleanly(self) -> set[str]:
        """The children that left on their own with status 0 (a robot whose battery ran dry)."""
        with self._lock:
            return {c.name for c in self.children.values()
                    if c.proc.poll() == 0 and c.name not in self.expected_exits and not self._stopping}

    def wait_for_news(self, timeout_s: float) -> None:
        """Sleep until the supervisor has events for `check_children` (a crash, a restart) or ``timeout_s``.

        Without a supervisor thread (no restart policy) nobody else looks: at most `SUPERVISE_IDLE_S`.
        """
        if self._supervisor_thread is None:
            time.sleep(max(0.0, min(timeout_s, SUPERVISE_IDLE_S)))
            return
        if self._news.wait(max(0.0, timeout_s)):
            self._news.clear()

    def _supervise(self) -> None:
        pidfds: dict[int, int] = {}  # pid -> its pidfd: readable once that child has exited
        try:
            while not self._stopping:
                events = self._supervise_once()
                if events:
                    with self._lock:
                        self._pending_events.extend(events)
                    self._news.set()
                self._wait_for_children(pidfds)
        finally:
            for fd in pidfds.values():
                os.close(fd)

    def _wait_for_children(self, pidfds: dict[int, int]) -> None:
        """Sleep until a watched child exits or a restart is due, rather than polling every 50 ms."""
        if not hasattr(os, "pidfd_open"):
            time.sleep(SUPERVISE_EVERY_S)
            return
        import select

        with self._lock:
            # a child that exited and was dealt with (reaped: returncode set) would keep its pidfd readable
            watched = {c.proc.pid for c in self.children.values()
                       if c.proc.returncode is None and c.name not in self.expected_exits and c.name not in self._down}
            due = self.supervisor.next_due() if self.supervisor is not None else None
        for pid in set(pidfds) - watched:
            os.close(pidfds.pop(pid))
        for pid in watched - set(pidfds):
            try:
                pidfds[pid] = os.pidfd_open(pid)
            except OSError:  # gone already: the next round sees it exited
                time.sleep(SUPERVISE_EVERY_S)
                return
        timeout = SUPERVISE_IDLE_S if due is None else min(SUPERVISE_IDLE_S, max(0.0, due - time.monotonic()))
        select.select(list(pidfds.values()), [], [], timeout)

    def _supervise_once(self) -> list[SupervisorEvent]:
        events: list[SupervisorEvent] = []
        with self._lock:
            for child in list(self.children.values()):
                if child.name in self.expected_exits or child.name in self._down or self._stopping:
                    continue
                rc = child.proc.poll()
                if rc in (None, 0):  # running, or left cleanly (a depleted robot): nothing to restart
                    continue
                if self.supervisor is None:
                    raise AutoPowerError(f"{child.name} exited with status {rc}; its log ({child.log_path}) "
                                         f"ends:\n{child.tail()}")
                self._down.add(child.name)
                event = self.supervisor.crashed(child.name, rc)
                log.warning("%s (log %s)", event.line(), child.log_path)
                events.append(event)
            if self.supervisor is not None and not self._stopping:
                for name in self.supervisor.due():
                    self.restart(name)
                    event = self.supervisor.restarted(name)
                    log.warning("%s", event.line())
                    events.append(event)
        for event in events:  # outside the lock: a file write need not hold up the callers
            self.record_event(event)
        return events

    def restart(self, name: str) -> None:
        """Start `name` again with the command it was started with."""
        self._spawn(name, self._commands[name])
        self._down.discard(name)

    def link_bytes(self) -> dict[str, int]:
        """Bytes each link's proxy carried so far, both directions ("A-B", names sorted): what the
        Zenoh sessions put on that radio, TLS and Zenoh framing, keep-alives and statuses
        included; {} with direct links (no proxy counts them)."""
        return {"-".join(sorted(pair)): proxy.bytes_forwarded for pair, proxy in self.proxies.items()}

    def supervision(self) -> dict:
        """What the supervisor did (for the live table and the summaries); {} without one."""
        if self.supervisor is None:
            return {}
        report = self.supervisor.report()
        report["down"] = sorted(self._down - set(report["given_up"]))  # waiting for their restart
        return report

    def record_event(self, event: SupervisorEvent) -> None:
        """Put a supervisor event into the run's recording (when the team records); never raises."""
        if self.spec.record_dir is None:
            return
        if self.mission is None:  # before the mission started there is no timeline to put it on
            log.info("supervisor event %s not recorded: the mission has not started", event.line())
            return
        try:
            from autopower.recording.recorder import record_fault_event

            record_fault_event(self.spec.record_dir, kind="crash", target=event.node, phase=event.kind,
                               reason=event.detail, mission=self.mission, wall_unix=event.t_unix)
        except Exception as exc:  # noqa: BLE001 - a recording problem must not stop the supervision
            log.warning("supervisor event %s not recorded: %s", event.line(), exc)

    def snapshot(self, timeout_s: float = 5.0, *, until_ready_s: float = 0.0) -> dict:
        return self.client.snapshot(timeout_s, until_ready_s=until_ready_s)

    def wait_ready(self, timeout_s: float = 60.0) -> dict:
        """Block until the base station reports every stage where the plan wants it."""
        deadline = time.monotonic() + timeout_s
        snap: dict = {}
        while time.monotonic() < deadline:
            self.check_children()
            given_up = self.supervisor.given_up() if self.supervisor else {}
            if given_up:  # a team that cannot start is not worth waiting for
                name, why = next(iter(given_up.items()))
                raise AutoPowerError(f"{name} could not be started ({why}); its log ({self.children[name].log_path}) "
                                     f"ends:\n{self.children[name].tail()}")
            # held by the base station until the team is ready (no snapshot every 50 ms while it
            # places the first plan), at most READY_HOLD_S so that a child that died is seen
            hold = max(0.0, min(READY_HOLD_S, deadline - time.monotonic()))
            asked = time.monotonic()
            try:
                snap = self.snapshot(timeout_s=max(0.5, min(3.0, deadline - time.monotonic())), until_ready_s=hold)
            except AutoPowerError:
                continue
            if snap.get("ready"):
                self.mission = self.mission or snap.get("mission")
                return snap
            if time.monotonic() - asked < hold:  # answered before its time (it holds no more queries)
                time.sleep(0.05)
        detail = json.dumps({k: snap.get(k) for k in ("placement", "target", "migrating", "plan_error", "events")},
                            indent=1) if snap else "no answer from the base station"
        raise AutoPowerError(f"the team was not ready within {timeout_s:g} s (logs in {self.log_dir}):\n{detail}")

    def stop(self, timeout_s: float = 8.0) -> dict[str, int | None]:
        """Stop the agents, then the base station; kill what does not stop in time."""
        with self._lock:
            self._stopping = True  # no restarts from here on
        if self._supervisor_thread is not None:
            self._supervisor_thread.join(timeout=2.0)
        if self.client is not None:
            self.client.close()
            self.client = None
        base = self.scenario.basestation
        order = [[n for n in self.children if n != base], [base]]
        for group in order:
            procs = [self.children[n] for n in group if n in self.children]
            for child in procs:
                if child.proc.poll() is None:
                    try:
                        child.proc.send_signal(signal.SIGCONT)  # a frozen child must hear the SIGTERM
                        child.proc.send_signal(signal.SIGTERM)
                    except ProcessLookupError:
                        pass
            deadline = time.monotonic() + timeout_s
            for child in procs:
                try:
                    child.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop in %.0f s; killing it", child.name, timeout_s)
                    child.proc.kill()
                    child.proc.wait(timeout=5)
                self.exit_codes[child.name] = child.proc.returncode
        if self._forkserver is not None:
            self._forkserver.close()  # it ends once its last child is reaped
        for proxy in self.proxies.values():
            proxy.close()
        self._remove_resume_files()
        if self.identities is not None:
            self.identities.remove()  # a stopped team's keys are of no use to anyone
        return {n: c for n, c in self.exit_codes.items() if n not in self.expected_exits}

    def exit_report(self, bad: dict[str, int | None], lines: int = 8) -> str:
        """What a user needs of children that exited with errors (or were killed): their codes, and
        how each one's log ends (a base station killed for not stopping says what it was doing)."""
        tails = [f"{name}'s log ends:\n{tail}" for name in sorted(bad) if name in self.children
                 and (tail := self.children[name].tail(lines))]
        return "\n".join([f"process(es) exited with errors: {bad}; logs in {self.log_dir}", *tails])

    def _remove_resume_files(self) -> None:
        """The agents' resume states (`autopower.agent.resume`) end with the team's mission, and so
        does the team's folder the processes made (an `up`'s session file keeps it until `up` ends)."""
        import shutil

        from autopower.agent.resume import AGENTS_DIR
        from autopower.basestation.operator import TEAMS_DIR, state_dir

        folder = state_dir() / TEAMS_DIR / self.team
        shutil.rmtree(folder / AGENTS_DIR, ignore_errors=True)
        try:
            folder.rmdir()
        except OSError:  # not empty (`up`'s session file, removed when it ends) or already gone
            pass

    def __enter__(self) -> "LocalTeam":
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
