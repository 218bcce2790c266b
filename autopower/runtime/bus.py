"""The Bus the processes talk through: a Zenoh adapter and an in-memory one for unit tests.

The agent and the base station only use this small surface (publish, subscribe, liveliness,
query/reply), so their logic runs unchanged on the `InMemoryBus` in unit tests and on
`ZenohBus` between real processes. Callbacks run on other threads (Zenoh's, or the thread that
drains a subscriber's bounded channel): they must only enqueue (the event loops do the work).

Zenoh traps this adapter handles (see docs/deploying/zenoh.md):
- the default congestion control drops under load: ``reliable=True`` publishes with BLOCK;
- one priority for everything lets chain frames starve the control plane on a slow link: frames
  go at Priority.DATA, the rest at DATA_HIGH (`protocol.keys.carries_chain_data`);
- failure detection is the dying peer's lease: it is a setting here (`ZenohSettings.lease_ms`);
- peers do not relay for other peers: every process connects explicitly to the endpoints it is
  given (one per peer pair, so a test can put a proxy on any single link), multicast and gossip
  scouting are off so nothing leaves loopback and parallel test runs cannot find each other;
- a callback subscriber buffers up to 256 samples of up to 1 GiB each on its way to Python: a
  subscriber here has an 8-sample channel and Zenoh takes no message over the codec's limit.

Not a Zenoh trap but one of ours: a node's status is its peers' heartbeat, and a loop held up by
one long event must not look like a cut link: `ZenohBus.repeat_until_next`.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Callable, Protocol

from autopower.protocol.codec import MAX_MESSAGE_BYTES
from autopower.protocol.keys import (  # noqa: F401  (the in-memory bus matches with key_matches)
    carries_chain_data,
    key_matches,
)

log = logging.getLogger(__name__)

MessageCallback = Callable[[str, bytes], None]
LivelinessCallback = Callable[[str, bool], None]


class Closeable(Protocol):
    def close(self) -> None: ...


class Request(Protocol):
    """An operator query: read ``payload``, ``reply`` once, then ``close``."""

    key: str
    payload: bytes

    def reply(self, payload: bytes) -> None: ...

    def close(self) -> None: ...


class Bus(Protocol):
    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None: ...

    def subscribe(self, key_expr: str, callback: MessageCallback) -> Closeable: ...

    def declare_token(self, key: str) -> Closeable: ...

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback) -> Closeable: ...

    def serve(self, key: str, callback: Callable[[Request], None]) -> Closeable: ...

    def query(self, key: str, payload: bytes, timeout_s: float = 2.0) -> list[bytes]: ...

    @property
    def zid(self) -> str: ...

    def links(self) -> dict[str, list[tuple[str, str]]]: ...

    def repeat_until_next(self, key: str, payload: bytes, after_s: float, every_s: float) -> None: ...

    def flush_recording(self) -> None: ...

    @property
    def repeated(self) -> int: ...

    def close(self) -> None: ...


# ---------------------------------------------------------------------------------------------
# Zenoh
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class TlsFiles:
    """A node's mutual-TLS material: the team CA, its certificate, its private key (paths)."""

    ca: str
    cert: str
    key: str


# The schemes a secure team's peer links may use. ``tls``: TLS over TCP. ``quic``: Zenoh's QUIC
# link (over UDP, TLS 1.3 inside, the same certificates), whose loss recovery resends a lost
# packet after about a round trip and numbers each resend anew (a lost resend is found as fast),
# where TCP waits at least 200 ms, doubles the wait each time and gives the connection up after
# `tcp_retries2`; on a lossy radio TCP's stalled stream blocks a reliable put until the team
# closes the link (docs/known-limits.md, "Lossy links and large teams").
TRANSPORTS = ("tls", "quic")


@dataclass(frozen=True, kw_only=True)
class ZenohSettings:
    """How one process joins Zenoh. Endpoints are explicit; nothing is discovered.

    With ``tls`` every link is mutual TLS against the team CA (endpoints are ``tls/...`` over TCP
    or ``quic/...``, see `TRANSPORTS`): the listener refuses a peer without a certificate of that
    CA, and each side learns the other's certificate name, which ``access_control`` (Zenoh's
    section, see `runtime.access_control`) uses to decide what that peer may put, declare or query
    here. Zenoh's QUIC link reads the same ``transport/link/tls`` section (TLS 1.3 is inside
    QUIC): on 1.10.2 it refuses a peer without a certificate or with another CA's, and access
    control matches its certificate's name as on a TLS link (tests/integration/test_security.py
    runs both). Zenoh traps handled: the connecting side must set ``enable_mtls`` too or it
    never sends its certificate; an ACL only holds when nobody can reach the node around it,
    hence scouting off.
    """

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    lease_ms: int = 1000  # a frozen peer or cut link is detected after about this long
    keep_alive: int = 4
    retry_init_ms: int = 100
    retry_max_ms: int = 500
    tls: TlsFiles | None = None
    access_control: dict | None = None  # Zenoh's access_control section (default deny)
    mode: str = "peer"
    # Zenoh moves every put over 3 KB into shared memory when both ends share a machine, so the
    # bytes never cross the link: False for nodes that stand for separate hosts (the testbed,
    # a fleet), where the link must carry what a radio would. None keeps Zenoh's default.
    shared_memory: bool | None = None
    # Zenoh reassembles a message of up to this many bytes (its default: 1 GiB) before anyone
    # can judge it; nothing larger than the codec's limit decodes, so nothing larger is taken.
    max_message_bytes: int = MAX_MESSAGE_BYTES

    def entries(self) -> list[tuple[str, object]]:
        """The configuration as (path, value) pairs: what `to_config` inserts, what a json5 file holds."""
        retry = {"period_init_ms": self.retry_init_ms, "period_max_ms": self.retry_max_ms,
                 "period_increase_factor": 2}
        out: list[tuple[str, object]] = [
            ("mode", self.mode),
            ("listen/endpoints", list(self.listen)),
            ("connect/endpoints", list(self.connect)),
            ("scouting/multicast/enabled", False),
            ("scouting/gossip/enabled", False),
            ("transport/link/tx/lease", int(self.lease_ms)),
            ("transport/link/tx/keep_alive", int(self.keep_alive)),
            # A reliable put to a peer whose link went silent blocks until its queue drains; Zenoh
            # closes the link only after this wait (default 5 s), and the publishing thread (a
            # process's event loop) is stuck all that time, as when a cut radio stops 230 KB camera
            # frames. A link that takes nothing for a lease is as dead as a silent one.
            ("transport/link/tx/queue/congestion_control/block/wait_before_close", int(self.lease_ms) * 1000),
            ("connect/retry", retry),
            # Keep retrying a peer that is not up yet instead of failing the open.
            ("connect/timeout_ms", -1),
            ("connect/exit_on_failure", False),
            ("transport/link/rx/max_message_size", int(self.max_message_bytes)),
        ]
        if self.tls is not None:
            out.append(("transport/link/tls", {
                "root_ca_certificate": self.tls.ca,
                "listen_certificate": self.tls.cert, "listen_private_key": self.tls.key,
                "connect_certificate": self.tls.cert, "connect_private_key": self.tls.key,
                "enable_mtls": True, "verify_name_on_connect": True,
            }))
        if self.access_control is not None:
            out.append(("access_control", self.access_control))
        if self.shared_memory is not None:
            out.append(("transport/shared_memory/enabled", self.shared_memory))
        return out

    def to_dict(self) -> dict:
        """The nested configuration (for a json5 file a node starts from)."""
        root: dict = {}
        for path, value in self.entries():
            *parents, leaf = path.split("/")
            node = root
            for part in parents:
                node = node.setdefault(part, {})
            node[leaf] = value
        return root

    def to_config(self):
        import zenoh

        cfg = zenoh.Config()
        for path, value in self.entries():
            cfg.insert_json5(path, json.dumps(value))
        return cfg


_zenoh_log_once = threading.Lock()
_zenoh_log_done = False


class _ZenohRequest:
    def __init__(self, query, key: str):
        self._query = query
        self.key = key
        payload = query.payload
        self.payload = payload.to_bytes() if payload is not None else b""
        self._closed = False

    def reply(self, payload: bytes) -> None:
        self._query.reply(self.key, payload)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._query.drop()


class ZenohBus:
    """A Bus over one Zenoh peer session (a context manager)."""

    def __init__(self, settings: ZenohSettings):
        import zenoh

        global _zenoh_log_done
        with _zenoh_log_once:
            if not _zenoh_log_done:
                zenoh.init_log_from_env_or("error")
                _zenoh_log_done = True
        self._zenoh = zenoh
        self.settings = settings
        self.session = zenoh.open(settings.to_config())
        self._zid = str(self.session.info.zid())  # a session's id never changes (read with every status)
        self._publishers: dict[tuple[str, bool], object] = {}
        self._pumps: set[_Pump] = set()
        self._lock = threading.Lock()
        self._closed = False
        self._repeater: _Repeater | None = None

    def __enter__(self) -> "ZenohBus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _publisher(self, key: str, reliable: bool):
        pub = self._publishers.get((key, reliable))
        if pub is None:
            with self._lock:
                pub = self._publishers.get((key, reliable))
                if pub is None:
                    cc, priority = self._zenoh.CongestionControl, self._zenoh.Priority
                    # Zenoh keeps a queue per priority and drains the higher one first; one queue
                    # for all let frames fill it on a slow radio, and a status (DROP) found it
                    # full for seconds on end: its peers and base station stopped hearing it
                    pub = self.session.declare_publisher(
                        key, congestion_control=cc.BLOCK if reliable else cc.DROP,
                        priority=priority.DATA if carries_chain_data(key, reliable) else priority.DATA_HIGH)
                    self._publishers[(key, reliable)] = pub
        return pub

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        if self._closed:
            return
        self._publisher(key, reliable).put(payload)

    def subscribe(self, key_expr: str, callback: MessageCallback):
        pump = _Pump(self.session, key_expr, callback, self._zenoh.handlers.FifoChannel(SUBSCRIBER_CHANNEL),
                     forget=self._pumps.discard)
        # held here: a subscriber with a channel is undeclared when dropped, and a caller that
        # drops the handle expects it to last until closed, as a callback subscriber does
        self._pumps.add(pump)
        return pump

    def declare_token(self, key: str):
        return _Undeclare(self.session.liveliness().declare_token(key))

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback):
        put = self._zenoh.SampleKind.PUT

        def on_sample(sample) -> None:
            callback(str(sample.key_expr), sample.kind == put)

        return _Undeclare(self.session.liveliness().declare_subscriber(key_expr, on_sample, history=True))

    def serve(self, key: str, callback: Callable[[Request], None]):
        def on_query(query) -> None:
            callback(_ZenohRequest(query, key))

        return _Undeclare(self.session.declare_queryable(key, on_query))

    def query(self, key: str, payload: bytes, timeout_s: float = 2.0) -> list[bytes]:
        out = []
        for reply in self.session.get(key, payload=payload, timeout=timeout_s):
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
        return out

    @property
    def zid(self) -> str:
        """This session's Zenoh id (what its peers' admin spaces call it)."""
        return self._zid

    def links(self, timeout_s: float = 1.0) -> dict[str, list[tuple[str, str]]]:
        """This session's links, by peer session: zid -> [(our endpoint, theirs)], from Zenoh's
        admin space (local: nothing crosses the network). Empty once closed."""
        if self._closed:
            return {}
        out: dict[str, list[tuple[str, str]]] = {}
        for reply in self.session.get(f"@/{self.zid}/session/transport/unicast/*/link/*", timeout=timeout_s):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/")
            try:
                link = json.loads(reply.ok.payload.to_bytes())
                src, dst = link["src"], link["dst"]
            except (ValueError, KeyError, TypeError):
                continue
            if len(parts) >= 7 and isinstance(src, str) and isinstance(dst, str):
                out.setdefault(parts[5], []).append((src, dst))
        return out

    def repeat_until_next(self, key: str, payload: bytes, after_s: float, every_s: float) -> None:
        """``payload`` was just put on ``key``; if no other follows within ``after_s``, put it again.

        For a node's status, the heartbeat its peers' silence detectors listen to: the loop that
        builds statuses can be held up by one long event (a stage run, a burst of inputs released
        at once by a resent frame) for longer than the peers wait, and an overloaded node then
        looked like a cut link. The copy goes out from a thread of ours, unreliable like the
        status itself, after ``after_s`` and then every ``every_s`` until the next status is put
        (more than one chance before a peer gives up: on a loaded machine this thread may wait
        for a core too), for at most `REPEAT_FOR_S` (a loop stuck for good must fall silent).
        Peers drop it as a duplicate (not newer than the last); what it proves is that this node
        and its link are there.
        """
        if self._closed:
            return
        with self._lock:
            if self._repeater is None:
                self._repeater = _Repeater(lambda k, p: self._publisher(k, False).put(p))
        self._repeater.arm(key, payload, after_s, every_s)

    def flush_recording(self) -> None:
        """Nothing to do: this bus records nothing (`RecordingBus.flush_recording`)."""

    @property
    def repeated(self) -> int:
        """How many copies `repeat_until_next` put so far (a loop that was late that often)."""
        return self._repeater.repeated if self._repeater is not None else 0

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._repeater is not None:
            self._repeater.stop()
        for pub in list(self._publishers.values()):
            try:
                pub.undeclare()
            except Exception:  # the session may already be going down
                pass
        self._publishers.clear()
        closing = threading.Thread(target=self._close_session, name="zenoh-close", daemon=True)
        closing.start()
        closing.join(SESSION_CLOSE_WAIT_S)
        if closing.is_alive():
            log.warning("the Zenoh session is still closing after %.0f s (a link that cannot flush what it "
                        "holds); not waiting for it: the process's exit closes its sockets", SESSION_CLOSE_WAIT_S)
        deadline = time.monotonic() + SESSION_CLOSE_WAIT_S
        for pump in list(self._pumps):
            pump.close(max(0.0, deadline - time.monotonic()))

    def _close_session(self) -> None:
        try:
            self.session.close()  # ends every pump's iteration
        except Exception as exc:  # Zenoh's own close timeout ("close operation timed out")
            log.warning("closing the Zenoh session: %s", exc)


# How long `ZenohBus.close` waits for Zenoh's own close. Zenoh waits up to 10 s for a link that
# cannot flush what it holds (a cut or lossy link: eclipse-zenoh/zenoh#2675) and then raises. A
# process stopping within its launcher's limit (`up`, the testbed: 8 s, then a kill) does not wait
# that out: the close goes on in the background, and the exit that follows closes the sockets
# (peers see the connection end, or their lease does it).
SESSION_CLOSE_WAIT_S = 2.0


# How many samples Zenoh holds for one subscriber before the link they come on waits (the
# sender is slowed down, nothing piles up here). A plain callback subscriber gets Zenoh's default:
# 256 samples of up to `max_message_size` each, a quarter of a gigabyte under a flood of 1 MB
# garbage on top of the event queue's own bound. The pump only moves a sample into the event
# queue (which bounds itself in bytes and counts what it drops), so a few are enough.
SUBSCRIBER_CHANNEL = 8


class _Pump:
    """A subscriber whose samples wait in a bounded Zenoh channel, taken out by a thread of ours.

    The thread reads the subscriber's *handler* (not the subscriber: a blocking ``recv`` on the
    subscriber would hold it borrowed and its undeclare would fail with "Already borrowed").
    Undeclaring the subscriber, or closing the session, ends the handler's iteration, so the
    thread ends with it. The callback runs on our thread, never on Zenoh's: undeclaring never
    waits for a callback that waits for the GIL.
    """

    def __init__(self, session, key_expr: str, callback: MessageCallback, channel,
                 forget: Callable[["_Pump"], None]):
        self._forget = forget
        self._sub = session.declare_subscriber(key_expr, channel)
        self._thread = threading.Thread(target=self._run, args=(self._sub.handler, callback),
                                        name=f"zenoh-sub {key_expr}", daemon=True)
        self._thread.start()

    @staticmethod
    def _run(handler, callback: MessageCallback) -> None:
        # recv() waits in slices of 100 ms with the GIL released: ~10 wake-ups a second at rest.
        for sample in handler:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:  # a callback only enqueues; never let one bad sample end the pump
                log.exception("subscriber callback failed on %s", sample.key_expr)

    def close(self, wait_s: float = 2.0) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # already undeclared, or the session is closed
            pass
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=wait_s)  # a daemon thread: one still reading ends with the process
        self._forget(self)


# A loop held up longer than this is as good as gone: its peers may stop counting on it.
REPEAT_FOR_S = 10.0


class _Repeater:
    """One thread that puts a key's last payload again while the loop that puts it is late."""

    def __init__(self, put: Callable[[str, bytes], None]):
        self._put = put
        self._cond = threading.Condition()
        self._armed: dict[str, tuple[bytes, float, float, float]] = {}  # key -> payload, every, due, until
        self._stopped = False
        self.repeated = 0
        self._thread = threading.Thread(target=self._run, name="status-repeater", daemon=True)
        self._thread.start()

    def arm(self, key: str, payload: bytes, after_s: float, every_s: float) -> None:
        now = time.monotonic()
        with self._cond:
            self._armed[key] = (payload, every_s, now + after_s, now + REPEAT_FOR_S)
            self._cond.notify()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while True:
            with self._cond:
                if self._stopped:
                    return
                now = time.monotonic()
                due = [k for k, (_, _, at, _) in self._armed.items() if at <= now]
                if not due:
                    # at rest: one wake-up per status put (each one re-arms), none in between
                    wake = min((at for _, _, at, _ in self._armed.values()), default=None)
                    self._cond.wait(None if wake is None else wake - now)
                    continue
                puts = []
                for key in due:
                    payload, every_s, _, until = self._armed.pop(key)
                    puts.append((key, payload))
                    if now + every_s < until:
                        self._armed[key] = (payload, every_s, now + every_s, until)
            for key, payload in puts:  # outside the lock: the loop arms the next one meanwhile
                try:
                    self._put(key, payload)
                    self.repeated += 1
                except Exception:  # the session is going down
                    log.debug("repeating %s failed", key, exc_info=True)


class _Undeclare:
    def __init__(self, entity):
        self._entity = entity

    def close(self) -> None:
        try:
            self._entity.undeclare()
        except Exception:  # already undeclared, or the session is closed
            pass


# ---------------------------------------------------------------------------------------------
# In memory
# ---------------------------------------------------------------------------------------------


@dataclass
class _Sub:
    bus: "InMemoryBus"
    key_expr: str
    callback: Callable
    liveliness: bool = False


class _MemRequest:
    def __init__(self, key: str, payload: bytes, sink: list[bytes]):
        self.key = key
        self.payload = payload
        self._sink = sink
        self.closed = False

    def reply(self, payload: bytes) -> None:
        if self.closed:
            raise RuntimeError("reply after close")
        self._sink.append(bytes(payload))

    def close(self) -> None:
        self.closed = True


@dataclass
class InMemoryHub:
    """The shared 'network' of InMemoryBus instances.

    With ``synchronous=False`` nothing is delivered until `pump` is called: a unit test then
    decides exactly when messages arrive (and can inspect them, drop them or reorder them).
    """

    synchronous: bool = True
    subs: list[_Sub] = field(default_factory=list)
    tokens: dict[str, int] = field(default_factory=dict)
    queryables: dict[str, tuple["InMemoryBus", Callable]] = field(default_factory=dict)
    pending: deque = field(default_factory=deque)
    published: list[tuple[str, bytes, bool]] = field(default_factory=list)
    record: bool = False

    def _deliver(self, call: Callable[[], None]) -> None:
        if self.synchronous:
            call()
        else:
            self.pending.append(call)

    def pump(self, limit: int = 1_000_000, rng=None) -> int:
        """Deliver queued messages (and whatever they cause) until none is left.

        With ``rng`` (a ``random.Random``) the next message is picked at random among those
        waiting: a harsher order than any real transport, for robustness tests.
        """
        n = 0
        while self.pending and n < limit:
            if rng is None:
                call = self.pending.popleft()
            else:
                i = rng.randrange(len(self.pending))
                self.pending.rotate(-i)
                call = self.pending.popleft()
                self.pending.rotate(i)
            call()
            n += 1
        return n

    def bus(self, name: str = "") -> "InMemoryBus":
        return InMemoryBus(self, name)


class InMemoryBus:
    """A Bus whose 'network' is an `InMemoryHub` in this process."""

    def __init__(self, hub: InMemoryHub | None = None, name: str = ""):
        self.hub = hub or InMemoryHub()
        self.name = name
        self._tokens: list[str] = []
        self._closed = False

    def __enter__(self) -> "InMemoryBus":
        return self

    zid = ""  # no Zenoh session, and no links whose bytes the kernel counts (`links`)

    def links(self) -> dict[str, list[tuple[str, str]]]:
        return {}

    def __exit__(self, *exc) -> None:
        self.close()

    def publish(self, key: str, payload: bytes, *, reliable: bool = True) -> None:
        if self._closed:
            return
        payload = bytes(payload)
        if self.hub.record:
            self.hub.published.append((key, payload, reliable))
        for sub in list(self.hub.subs):
            if not sub.liveliness and not sub.bus._closed and key_matches(sub.key_expr, key):
                self.hub._deliver(lambda cb=sub.callback: cb(key, payload))

    def subscribe(self, key_expr: str, callback: MessageCallback):
        sub = _Sub(self, key_expr, callback)
        self.hub.subs.append(sub)
        return _MemHandle(lambda: self._remove(sub))

    def _remove(self, sub: _Sub) -> None:
        if sub in self.hub.subs:
            self.hub.subs.remove(sub)

    def _notify(self, key: str, alive: bool) -> None:
        for sub in list(self.hub.subs):
            if sub.liveliness and key_matches(sub.key_expr, key):
                self.hub._deliver(lambda cb=sub.callback: cb(key, alive))

    def declare_token(self, key: str):
        self.hub.tokens[key] = self.hub.tokens.get(key, 0) + 1
        self._tokens.append(key)
        if self.hub.tokens[key] == 1:
            self._notify(key, True)
        return _MemHandle(lambda: self._undeclare(key))

    def _undeclare(self, key: str) -> None:
        if key not in self._tokens:
            return
        self._tokens.remove(key)
        self.hub.tokens[key] -= 1
        if self.hub.tokens[key] == 0:
            del self.hub.tokens[key]
            self._notify(key, False)

    def watch_liveliness(self, key_expr: str, callback: LivelinessCallback):
        sub = _Sub(self, key_expr, callback, liveliness=True)
        self.hub.subs.append(sub)
        for key in list(self.hub.tokens):  # history: tokens already present
            if key_matches(key_expr, key):
                self.hub._deliver(lambda k=key: callback(k, True))
        return _MemHandle(lambda: self._remove(sub))

    def serve(self, key: str, callback: Callable[[Request], None]):
        self.hub.queryables[key] = (self, callback)
        return _MemHandle(lambda: self.hub.queryables.pop(key, None))

    def query(self, key: str, payload: bytes, timeout_s: float = 2.0) -> list[bytes]:
        replies: list[bytes] = []
        for qkey, (bus, callback) in list(self.hub.queryables.items()):
            if not bus._closed and key_matches(qkey, key):
                callback(_MemRequest(qkey, bytes(payload), replies))
        return replies

    def repeat_until_next(self, key: str, payload: bytes, after_s: float, every_s: float) -> None:
        """Nothing to do: an in-memory loop is never late for its peers (unit tests drive time)."""

    def flush_recording(self) -> None:
        """Nothing to do: this bus records nothing."""

    repeated = 0

    def close(self) -> None:
        if self._closed:
            return
        for key in list(self._tokens):
            self._undeclare(key)
        self._closed = True
        self.hub.subs = [s for s in self.hub.subs if s.bus is not self]
        for qkey, (bus, _) in list(self.hub.queryables.items()):
            if bus is self:
                del self.hub.queryables[qkey]


class _MemHandle:
    def __init__(self, fn: Callable[[], None]):
        self._fn = fn

    def close(self) -> None:
        fn, self._fn = self._fn, None
        if fn is not None:
            fn()
