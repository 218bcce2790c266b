"""What a node's Zenoh session really puts on each of its links, read from the kernel (Linux).

A robot's radios carry more than its chains' messages: statuses, liveliness, Zenoh's keep-alives
and their acknowledgements, plans, orders, votes, signatures, and the Zenoh, TLS, TCP and IP
framing of everything. The meter charges the chains' messages as the model prices them; this
module measures all the bytes, per peer, so that the rest can be charged as the node's own
``control`` part (`autopower.node.control_meter`).

Two sources, both inside the process:
- Zenoh's admin space names each peer session and its links (``@/<zid>/session/transport/unicast/
  <peer zid>/link/<id>``: ``src`` is our address, ``dst`` theirs): `ZenohBus.links`;
- the kernel's ``TCP_INFO`` of each TCP socket this process holds (found under /proc/self/fd)
  counts the payload bytes it sent (retransmissions included: the radio sends them again) and
  received, and the segments each way. Every segment also carries its IP and TCP headers (with
  the timestamp option when the connection uses it): counted per segment.

What it cannot see, said where the figures are shown: the bytes of a connection that opened and
closed between two polls (those since the last poll), links that are not TCP (Zenoh's UDP and
QUIC: AutoPower configures neither), and what lies below IP (a radio's own framing, which the
model's bandwidth figure stands for).
"""

from __future__ import annotations

import ipaddress
import os
import socket
import struct
import sys
from dataclasses import dataclass
from typing import Iterable, Mapping

# struct tcp_info (linux/tcp.h): the offsets of the fields read here (stable kernel ABI since 4.19)
_TCPI_OPTIONS = 5  # __u8 tcpi_options
_TCPI_BYTES_RECEIVED = 128  # __u64 tcpi_bytes_received (payload received, RFC 4898)
_TCPI_SEGS = 136  # __u32 tcpi_segs_out, tcpi_segs_in (all segments, bare ACKs and retransmissions too)
_TCPI_BYTES_SENT = 200  # __u64 tcpi_bytes_sent (payload sent, retransmissions included; kernel >= 4.19)
_TCPI_LEN = _TCPI_BYTES_SENT + 8
_TCPI_OPT_TIMESTAMPS = 1
_TCP_HEADER, _TIMESTAMP_OPTION = 20, 12
_IP_HEADER = {socket.AF_INET: 20, socket.AF_INET6: 40}

Address = tuple[str, int]  # (IP in its canonical text form, port)
# wall seconds between two readings: a node reads its links with its status, at most this often
# (each reading asks Zenoh's admin space and reads every socket: about a millisecond per dozen links)
POLL_EVERY_S = 2.0
# a socket missing from a reading (its descriptor listed as another between listing and reading, a
# short read of /proc) keeps its last totals this many readings: seen again, it adds only its growth
KEEP_UNSEEN_READINGS = 5


@dataclass(frozen=True)
class SocketTotals:
    """One TCP connection's bytes each way since it opened: its payload, and the IP and TCP headers
    of its segments (what the radio carries is their sum)."""

    payload_sent: int
    payload_received: int
    headers_sent: int = 0
    headers_received: int = 0
    segments_sent: int = 0  # the packets the radio carries, bare ACKs and retransmissions included
    segments_received: int = 0

    @property
    def sent(self) -> int:
        return self.payload_sent + self.headers_sent

    @property
    def received(self) -> int:
        return self.payload_received + self.headers_received


def supported() -> bool:
    """Can this machine count a socket's bytes (Linux, with /proc)?"""
    return sys.platform.startswith("linux") and os.path.isdir("/proc/self/fd")


def canonical(host: str, port: int) -> Address:
    """An address as the kernel and Zenoh may spell it differently: an IPv4-mapped IPv6 address is
    the IPv4 one, and every IP in its compressed text form."""
    try:
        ip = ipaddress.ip_address(host.strip("[]").split("%")[0])
    except ValueError:
        return host, int(port)
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return str(ip), int(port)


def parse_endpoint(endpoint: str) -> Address | None:
    """``tcp/127.0.0.1:7447`` or ``tls/[::1]:7447`` (metadata after ``?`` or ``#`` ignored) as an
    address; None for what is not ``protocol/host:port``."""
    _, sep, rest = endpoint.partition("/")
    if not sep:
        return None
    rest = rest.split("?")[0].split("#")[0]
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return canonical(host, int(port))


def _totals(sock: socket.socket) -> SocketTotals | None:
    info = sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 256)
    if len(info) < _TCPI_LEN:
        return None  # a kernel older than 4.19: no tcpi_bytes_sent
    (received,) = struct.unpack_from("Q", info, _TCPI_BYTES_RECEIVED)
    segs_out, segs_in = struct.unpack_from("II", info, _TCPI_SEGS)
    (sent,) = struct.unpack_from("Q", info, _TCPI_BYTES_SENT)
    header = _IP_HEADER.get(sock.family, 20) + _TCP_HEADER
    if info[_TCPI_OPTIONS] & _TCPI_OPT_TIMESTAMPS:
        header += _TIMESTAMP_OPTION
    return SocketTotals(payload_sent=sent, payload_received=received, headers_sent=segs_out * header,
                        headers_received=segs_in * header, segments_sent=segs_out, segments_received=segs_in)


def tcp_connections() -> dict[tuple[Address, Address], tuple[str, SocketTotals]]:
    """Every connected TCP socket of this process: (ours, theirs) -> (the socket's inode, totals).

    A socket is read through a duplicate of its descriptor (closing the duplicate leaves the
    owner's socket open); one closed meanwhile, or whose number now names something else, is
    skipped."""
    out: dict[tuple[Address, Address], tuple[str, SocketTotals]] = {}
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return out
    for fd in fds:
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if not target.startswith("socket:"):
            continue
        try:
            dup = os.dup(int(fd))
        except OSError:
            continue
        try:
            sock = socket.socket(fileno=dup)
        except OSError:
            os.close(dup)
            continue
        try:
            if sock.family not in _IP_HEADER or sock.type != socket.SOCK_STREAM:
                continue
            ours, theirs = sock.getsockname(), sock.getpeername()
            totals = _totals(sock)
        except OSError:  # not connected (a listener), or gone
            continue
        finally:
            sock.close()
        if totals is not None:
            out[(canonical(*ours[:2]), canonical(*theirs[:2]))] = (target, totals)
    return out


class LinkTraffic:
    """The bytes this process's Zenoh session exchanged with each peer session so far.

    Polled (`poll`) at the node's status cadence: each connection's growth since the last poll is
    added to its peer's totals, so a connection that closes and reopens keeps adding up."""

    def __init__(self, every_s: float = POLL_EVERY_S) -> None:
        self.every_s = every_s
        self._next = 0.0  # monotonic time of the next reading (`due`)
        # socket inode -> (its totals when last read, readings since): a socket read again adds its growth
        self._last: dict[str, tuple[SocketTotals, int]] = {}
        self.by_peer: dict[str, tuple[int, int]] = {}  # peer zid -> (sent, received) since the start
        self.payload_by_peer: dict[str, tuple[int, int]] = {}  # of these, TCP's payload (headers left out)
        self.packets_by_peer: dict[str, tuple[int, int]] = {}  # peer zid -> (segments sent, received) since the start
        self.unattributed = (0, 0)  # TCP bytes on connections no Zenoh link names (not ours to price)

    def due(self, now: float) -> bool:
        """Is a reading due at monotonic time ``now``? (True at most once per ``every_s``.)"""
        if now < self._next:
            return False
        self._next = now + self.every_s
        return True

    def poll(self, links: Mapping[str, Iterable[tuple[str, str]]],
             connections: Mapping[tuple[Address, Address], tuple[str, SocketTotals]] | None = None
             ) -> dict[str, tuple[int, int]]:
        """Add what each connection carried since the last poll; the totals by peer zid.

        ``links``: peer zid -> its links' (src, dst) endpoints (`ZenohBus.links`);
        ``connections``: `tcp_connections()` (read now when not given)."""
        if connections is None:
            connections = tcp_connections()
        peer_of: dict[tuple[Address, Address], str] = {}
        for zid, pairs in links.items():
            for src, dst in pairs:
                ours, theirs = parse_endpoint(src), parse_endpoint(dst)
                if ours is not None and theirs is not None:
                    peer_of[(ours, theirs)] = zid
        seen: dict[str, tuple[SocketTotals, int]] = {}
        for pair, (inode, totals) in connections.items():
            seen[inode] = (totals, 0)
            before = self._last.get(inode, (SocketTotals(0, 0), 0))[0]
            grew = (max(0, totals.sent - before.sent), max(0, totals.received - before.received))
            zid = peer_of.get(pair)
            if zid is None:
                self.unattributed = _plus(self.unattributed, grew)
                continue
            self.by_peer[zid] = _plus(self.by_peer.get(zid, (0, 0)), grew)
            self.payload_by_peer[zid] = _plus(self.payload_by_peer.get(zid, (0, 0)),
                                              (max(0, totals.payload_sent - before.payload_sent),
                                               max(0, totals.payload_received - before.payload_received)))
            self.packets_by_peer[zid] = _plus(self.packets_by_peer.get(zid, (0, 0)),
                                              (max(0, totals.segments_sent - before.segments_sent),
                                               max(0, totals.segments_received - before.segments_received)))
        for inode, (totals, missed) in self._last.items():
            if inode not in seen and missed + 1 < KEEP_UNSEEN_READINGS:
                seen[inode] = (totals, missed + 1)
        self._last = seen
        return dict(self.by_peer)


def _plus(a: tuple[int, int], b: tuple[int, int]) -> tuple[int, int]:
    return a[0] + b[0], a[1] + b[1]


def link_traffic_of(bus) -> LinkTraffic | None:
    """A reader for ``bus``'s links, or None where nothing can be read (not Linux, no Zenoh session)."""
    return LinkTraffic() if supported() and bus.zid else None
