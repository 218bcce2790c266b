"""Radio links on localhost: a TCP forwarder per link that a fault can cut silently.

Every Zenoh connection between two nodes goes through the LinkProxy of their link. `cut()`
keeps every socket open but stops moving bytes in both directions and accepts new connections
without ever answering them: what a robot sees when its peer drives out of radio range — no FIN,
no RST, no goodbye. Only the Zenoh lease can notice, which is what we want to measure.
`heal()` closes the black-holed connections (they are dead to both ends already) and forwards
again, so the sessions reconnect.

One thread per link, asleep in `select` until a socket has bytes: a team at rest still moves a
keep-alive each way on each link several times a second, and one loop that reads into a buffer
it reuses costs less per message than a thread per direction woken for each (measured in
bench/bench_idle.py). Sockets are non-blocking: what a receiver cannot take yet waits in a
buffer and that direction stops reading until it is taken (the other direction flows on; a
slow reader never stalls its peer's traffic towards it). Everything binds to 127.0.0.1.
"""

from __future__ import annotations

import logging
import selectors
import socket
import threading
import time

log = logging.getLogger(__name__)
CHUNK = 1 << 16


class _Conn:
    """One forwarded connection: two sockets, and per direction what the receiver has not taken yet."""

    def __init__(self, client: socket.socket, upstream: socket.socket | None):
        self.client, self.upstream = client, upstream
        self.pending: dict[socket.socket, bytearray] = {client: bytearray()}  # socket -> bytes waiting for it
        if upstream is not None:
            self.pending[upstream] = bytearray()
        self.eof: set[socket.socket] = set()  # ends that closed while the link was cut

    def peer(self, s: socket.socket) -> socket.socket | None:
        return self.upstream if s is self.client else self.client

    def sockets(self) -> list[socket.socket]:
        return [s for s in (self.client, self.upstream) if s is not None]


class LinkProxy:
    """Forward 127.0.0.1:<port> to a target address until cut; see the module docstring."""

    def __init__(self, name: str, target_port: int, *, listen_port: int = 0, target_host: str = "127.0.0.1",
                 server: socket.socket | None = None):
        """``server``: accept on this listening socket instead (e.g. one bound in another namespace)."""
        self.name = name
        self.target = (target_host, target_port)
        self._server = server or socket.create_server(("127.0.0.1", listen_port), reuse_port=False)
        self._server.setblocking(False)
        self.port = self._server.getsockname()[1]
        self._cut = False
        self._closed = False
        self._lock = threading.Lock()  # the requests below, between a caller and the loop
        self._requests: list[tuple[str, threading.Event]] = []
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._conns: dict[socket.socket, _Conn] = {}  # either socket -> its connection (the loop's alone)
        self._buffer = bytearray(CHUNK)
        self.cut_at: float | None = None
        self.bytes_forwarded = 0
        self.bytes_dropped = 0
        self._thread = threading.Thread(target=self._loop, name=f"link-{name}", daemon=True)

    # ---- lifecycle ---------------------------------------------------------------------------
    def __enter__(self) -> "LinkProxy":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> "LinkProxy":
        self._selector.register(self._server, selectors.EVENT_READ)
        self._selector.register(self._wake_r, selectors.EVENT_READ)
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():
            self._request("close")
            self._thread.join(timeout=2)
        else:
            self._closed = True
            self._shut()

    @property
    def is_cut(self) -> bool:
        return self._cut

    def cut(self) -> None:
        """Silently stop all traffic on this link (sockets stay open, nothing is answered)."""
        if not self._cut:
            self.cut_at = time.monotonic()
            self._cut = True  # the loop drops what it reads from now on
            self._request("cut")
            log.info("link %s cut", self.name)

    def heal(self) -> None:
        """Let traffic flow again; black-holed connections are dropped so the ends reconnect."""
        if self._cut:
            self._request("heal")
            self.cut_at = None
            log.info("link %s healed", self.name)

    def _request(self, what: str) -> None:
        """Have the loop do ``what`` (it alone touches the sockets) and wait until it did."""
        done = threading.Event()
        with self._lock:
            self._requests.append((what, done))
        try:
            self._wake_w.send(b"\0")
        except OSError:  # the wake-up pipe is full (the loop is on its way) or closed (no loop)
            pass
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            done.wait(timeout=2)

    # ---- the loop ----------------------------------------------------------------------------
    def _loop(self) -> None:
        try:
            while not self._closed:
                for key, events in self._selector.select():
                    s = key.fileobj
                    if s is self._wake_r:
                        self._take_requests()
                        if self._closed:
                            return
                    elif s is self._server:
                        self._accept()
                    elif s in self._conns:  # not closed by an earlier event of this round
                        if events & selectors.EVENT_WRITE:
                            self._flush(s)
                        if events & selectors.EVENT_READ and s in self._conns:
                            self._read(s)
        finally:
            self._shut()

    def _take_requests(self) -> None:
        try:
            while self._wake_r.recv(4096):
                pass
        except OSError:
            pass
        with self._lock:
            requests, self._requests = self._requests, []
        for what, done in requests:
            if what == "close":
                self._closed = True
            elif what == "cut":
                for conn in set(self._conns.values()):  # what waited for a receiver is lost with the radio
                    for s, waiting in conn.pending.items():
                        self.bytes_dropped += len(waiting)
                        waiting.clear()
                    self._watch(conn)
            elif what == "heal":
                for conn in set(self._conns.values()):
                    self._drop(conn)
                self._cut = False
            done.set()

    def _accept(self) -> None:
        try:
            client, _ = self._server.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # closed under us
            self._closed = True
            return
        client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if self._cut:
            # out of range: the connection is never answered; keep it so it does not RST
            conn = _Conn(client, None)
            self._conns[client] = conn
            return
        try:
            upstream = socket.create_connection(self.target, timeout=2)  # loopback: at once, or refused
            upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        except OSError as exc:
            log.debug("link %s: target %s unreachable: %s", self.name, self.target, exc)
            client.close()
            return
        client.setblocking(False)
        upstream.setblocking(False)
        conn = _Conn(client, upstream)
        self._conns[client] = self._conns[upstream] = conn
        for s in conn.sockets():
            self._selector.register(s, selectors.EVENT_READ)

    def _read(self, src: socket.socket) -> None:
        conn = self._conns[src]
        try:
            n = src.recv_into(self._buffer)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            n = 0
        if n == 0:  # that end closed for real (a process exited)
            if self._cut:  # silence is the point: the other end hears nothing of it
                conn.eof.add(src)
                self._watch(conn)
            else:
                self._drop(conn)  # pass it on
            return
        if self._cut:
            self.bytes_dropped += n  # swallowed: the radio is out of range
            return
        dst = conn.peer(src)
        data = memoryview(self._buffer)[:n]
        sent = 0
        if not conn.pending[dst]:
            try:
                sent = dst.send(data)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self._drop(conn)
                return
        self.bytes_forwarded += sent
        if sent < n:  # the receiver is slow: keep the rest, stop reading this direction until it is taken
            conn.pending[dst] += data[sent:]
            self._watch(conn)

    def _flush(self, dst: socket.socket) -> None:
        conn = self._conns[dst]
        waiting = conn.pending[dst]
        try:
            sent = dst.send(waiting)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(conn)
            return
        self.bytes_forwarded += sent
        del waiting[:sent]
        if not waiting:
            self._watch(conn)

    def _watch(self, conn: _Conn) -> None:
        """Register what each socket of ``conn`` waits for: to be read unless its peer has bytes
        waiting (or it closed), to be written while bytes wait for it."""
        for s in conn.sockets():
            if s not in self._conns or conn.upstream is None:
                continue
            peer = conn.peer(s)
            events = 0
            if not conn.pending[peer] and s not in conn.eof:
                events |= selectors.EVENT_READ
            if conn.pending[s]:
                events |= selectors.EVENT_WRITE
            try:
                if events:
                    self._selector.modify(s, events)
                else:
                    self._selector.unregister(s)
            except KeyError:
                if events:
                    self._selector.register(s, events)

    def _drop(self, conn: _Conn) -> None:
        for s in conn.sockets():
            self._conns.pop(s, None)
            try:
                self._selector.unregister(s)
            except (KeyError, ValueError):
                pass
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            s.close()

    def _shut(self) -> None:
        for conn in set(self._conns.values()):
            self._drop(conn)
        for s in (self._server, self._wake_r, self._wake_w):
            try:
                s.close()
            except OSError:
                pass
        self._selector.close()


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (racy by nature; callers retry on bind failure)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
