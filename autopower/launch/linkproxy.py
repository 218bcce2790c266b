"""Radio links on localhost: a TCP forwarder per link that a fault can cut silently.

Every Zenoh connection between two nodes goes through the LinkProxy of their link. `cut()`
keeps every socket open but stops moving bytes in both directions and accepts new connections
without ever answering them: what a robot sees when its peer drives out of radio range — no FIN,
no RST, no goodbye. Only the Zenoh lease can notice, which is what we want to measure.
`heal()` closes the black-holed connections (they are dead to both ends already) and forwards
again, so the sessions reconnect.

Blocking sockets with a thread per direction: a handful of links, a few connections each; simple
beats clever here. Everything binds to 127.0.0.1.
"""

from __future__ import annotations

import logging
import socket
import threading
import time

log = logging.getLogger(__name__)
CHUNK = 1 << 16


class LinkProxy:
    """Forward 127.0.0.1:<port> to a target address until cut; see the module docstring."""

    def __init__(self, name: str, target_port: int, *, listen_port: int = 0, target_host: str = "127.0.0.1",
                 server: socket.socket | None = None):
        """``server``: accept on this listening socket instead (e.g. one bound in another namespace)."""
        self.name = name
        self.target = (target_host, target_port)
        self._server = server or socket.create_server(("127.0.0.1", listen_port), reuse_port=False)
        self._server.settimeout(None)  # accept blocks; `close` wakes it (no wake-up every 0.2 s at rest)
        self.port = self._server.getsockname()[1]
        self._cut = threading.Event()
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._conns: list[tuple[socket.socket, socket.socket | None]] = []
        self.cut_at: float | None = None
        self.bytes_forwarded = 0
        self.bytes_dropped = 0
        self._acceptor = threading.Thread(target=self._accept_loop, name=f"link-{name}", daemon=True)

    # ---- lifecycle ---------------------------------------------------------------------------
    def __enter__(self) -> "LinkProxy":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> "LinkProxy":
        self._acceptor.start()
        return self

    def close(self) -> None:
        self._closed.set()
        try:
            self._server.shutdown(socket.SHUT_RDWR)  # wakes the blocked accept (Linux)
        except OSError:
            pass
        self._server.close()
        self._close_all()
        if self._acceptor.is_alive():
            self._acceptor.join(timeout=2)

    @property
    def is_cut(self) -> bool:
        return self._cut.is_set()

    def cut(self) -> None:
        """Silently stop all traffic on this link (sockets stay open, nothing is answered)."""
        if not self._cut.is_set():
            self.cut_at = time.monotonic()
            self._cut.set()
            log.info("link %s cut", self.name)

    def heal(self) -> None:
        """Let traffic flow again; black-holed connections are dropped so the ends reconnect."""
        if self._cut.is_set():
            self._close_all()
            self._cut.clear()
            self.cut_at = None
            log.info("link %s healed", self.name)

    # ---- forwarding --------------------------------------------------------------------------
    def _accept_loop(self) -> None:
        while not self._closed.is_set():
            try:
                client, _ = self._server.accept()
            except OSError:  # closed (shut down under a blocked accept)
                return
            if self._closed.is_set():
                client.close()
                return
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            if self._cut.is_set():
                # out of range: the connection is never answered; keep it so it does not RST
                with self._lock:
                    self._conns.append((client, None))
                continue
            try:
                upstream = socket.create_connection(self.target, timeout=2)
                upstream.settimeout(None)
                upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError as exc:
                log.debug("link %s: target %s unreachable: %s", self.name, self.target, exc)
                client.close()
                continue
            with self._lock:
                self._conns.append((client, upstream))
            for src, dst in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(src, dst), daemon=True,
                                 name=f"link-{self.name}-pump").start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while True:
                data = src.recv(CHUNK)
                if not data:
                    break
                if self._cut.is_set():
                    self.bytes_dropped += len(data)  # swallowed: the radio is out of range
                    continue
                dst.sendall(data)
                with self._lock:  # two pumps per connection add to it
                    self.bytes_forwarded += len(data)
        except OSError:
            pass
        finally:
            # One side closed for real (a process exited): pass that on unless we are cut,
            # in which case silence is the point.
            if not self._cut.is_set():
                for s in (src, dst):
                    try:
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass

    def _close_all(self) -> None:
        with self._lock:
            conns, self._conns = self._conns, []
        for client, upstream in conns:
            for s in (client, upstream):
                if s is not None:
                    try:
                        # close() alone neither wakes a pump blocked in recv on it nor sends a FIN
                        # while that recv holds the socket: shut it down first
                        s.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass
                    try:
                        s.close()
                    except OSError:
                        pass


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (racy by nature; callers retry on bind failure)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
