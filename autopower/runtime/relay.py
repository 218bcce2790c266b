"""Application-level relay of the control plane: plans, control, inbox replies and statuses.

Zenoh peers do not relay for other peers (zenoh >= 1.9), and a robot whose radio link to the
base station is cut is still in the team if another robot reaches both. So every process keeps
a `Relayer`: it knows which nodes it sees directly (their liveliness tokens) and what every
other node reports seeing (the ``links`` of their statuses), and sends a message either
directly or wrapped in a `Relayed` along the shortest path of that reported graph. Each node
on the way hands it to the next; the destination handles it as if it had arrived on its key.

Pure logic over a `Bus`: no threads, no clock; the owning process feeds it liveliness changes,
statuses and the relay messages addressed to it.
"""

from __future__ import annotations

import dataclasses
import logging
from collections import deque
from typing import Callable

from autopower.errors import ProtocolError
from autopower.protocol import Keys, NodeStatus, PeerStatus, Relayed, decode, encode
from autopower.protocol.access import TeamAccess
from autopower.runtime.bus import Bus
from autopower.runtime.signatures import Signing

log = logging.getLogger(__name__)

MAX_HOPS = 8


class Relayer:
    """Send to a node directly when it is in sight, else through the nodes that reach it."""

    def __init__(self, *, node: str, bus: Bus, keys: Keys, count: Callable[[str, str], None] | None = None,
                 access: TeamAccess | None = None, signing: Signing | None = None,
                 team: tuple[str, ...] | None = None):
        """With ``access``, a relayed message is delivered only if its origin may put on its key;
        with ``signing``, what we originate is signed and what reaches us must be signed by its
        claimed origin (a robot on the way cannot write in another node's name). ``team``: its
        members (default: ``access``'s), what a status naming the nodes out of sight is read against
        (`PeerStatus.sees`)."""
        self.node = node
        self.access = access
        self.team = team if team is not None else access.members if access is not None else ()
        self.signing = signing
        self.bus = bus
        self.keys = keys
        self.direct: set[str] = set()
        # nodes still "in sight" by our lease that have told us (by relaying to us, and by a status
        # that does not list us: `_shuns`) that we are not in theirs: our link to them is cut and
        # our lease has not expired yet
        self.shunned: set[str] = set()
        self.views: dict[str, set[str]] = {}  # node -> the nodes it reported seeing, from its last status
        self._count = count or (lambda what, detail="": None)
        self.relayed_out = 0
        self.forwarded = 0

    # ---- what we know ----------------------------------------------------------------------------------
    def on_liveliness(self, node: str, alive: bool) -> None:
        if node == self.node:
            return
        self.shunned.discard(node)
        if alive:
            self.direct.add(node)
        else:
            self.direct.discard(node)

    def on_direct(self, node: str) -> None:
        """A message from ``node`` arrived directly, not relayed: our link to it works.

        Undoes a shun: the relayed message that caused it may have been sent before the link came
        back and arrived after (it went the long way), which must not cut us off from a node we see.
        Every direct copy counts, the duplicate of a relayed one too: a node that shunned us relays
        its statuses to us beside the direct copy, we shun it back on the relayed one, and, if the
        direct copy were dropped as a duplicate, each would send the other everything through a
        third node for good (seen in a 20-robot testbed: one robot's camera frames to the base
        station all crossed a neighbour's radio, 43 MB in 9 s).
        """
        if node in self.shunned:
            self.shunned.discard(node)
            self.direct.add(node)

    def on_status(self, status: NodeStatus | PeerStatus) -> None:
        if status.node != self.node:
            self.views[status.node] = (status.sees(self.team) if isinstance(status, PeerStatus)
                                       else {n for n, up in status.links.items() if up})
            if status.node in self.shunned and self.node in self.views[status.node]:
                # it sees us again by its own report (our token reaches it): the cut is over
                self.shunned.discard(status.node)
                self.direct.add(status.node)

    def _shuns(self, origin: str) -> bool:
        """Does a relayed message from ``origin``, a node we see, show that it cannot hear us?

        Only if its last status does not list us among the nodes it sees (or none came yet). A node
        that sees us may relay to us for another reason: it shunned us on a relayed message of ours.
        Taking that as a cut made two nodes shun each other for good, each relaying everything for
        the other through a third (a 20-robot testbed: 43 MB of one robot's camera frames crossed a
        neighbour's radio in 9 s)."""
        return origin in self.direct and self.node not in self.views.get(origin, set())

    def forget(self, node: str) -> None:
        self.views.pop(node, None)

    def path_to(self, dest: str) -> list[str] | None:
        """Shortest path over direct links (ours) and reported ones (theirs); None if none."""
        if dest == self.node:
            return [dest]
        prev: dict[str, str] = {self.node: ""}
        todo = deque([self.node])
        while todo:
            u = todo.popleft()
            nbrs = self.direct if u == self.node else self.views.get(u, set())
            for v in sorted(nbrs):
                if v in prev:
                    continue
                # a reported edge counts only if its far end is not ourselves going backwards
                prev[v] = u
                if v == dest:
                    path = [v]
                    while prev[path[-1]]:
                        path.append(prev[path[-1]])
                    return path[::-1]
                todo.append(v)
        return None

    def reachable(self, dest: str) -> bool:
        return self.path_to(dest) is not None

    def reached(self) -> set[str]:
        """Every node `reachable` says we reach (ourselves included), found by one search over the
        same links: a robot that asks about each of the team's robots in turn makes one search per
        robot, and the work grows with the square of the team (`SubgroupRounds.tick`)."""
        seen = {self.node}
        todo = deque([self.node])
        while todo:
            u = todo.popleft()
            for v in self.direct if u == self.node else self.views.get(u, ()):
                if v not in seen:
                    seen.add(v)
                    todo.append(v)
        return seen

    # ---- sending -----------------------------------------------------------------------------------------
    def send(self, dest: str, key: str, payload: bytes, *, reliable: bool = True) -> bool:
        """Publish ``payload`` on ``key`` for ``dest``: directly if in sight, else relayed."""
        if dest == self.node or dest in self.direct:
            self.bus.publish(key, payload, reliable=reliable)
            return True
        path = self.path_to(dest)
        if path is None or len(path) > MAX_HOPS:
            self._count("no-relay-path", f"{dest} is out of reach from {self.node}")
            return False
        msg = Relayed(path=tuple(path), hop=1, key=key, payload=payload)
        if self.signing is not None:
            msg = self.signing.sign(msg)  # over hop 1: the hop is all a forwarder changes
        self.bus.publish(self.keys.node_relay(path[1]), encode(msg), reliable=reliable)
        self.relayed_out += 1
        return True

    def send_beyond_sight(self, dests, key: str, payload: bytes, *, reliable: bool = True) -> None:
        """For a broadcast already published directly: also relay it to those out of sight."""
        for dest in dests:
            if dest != self.node and dest not in self.direct and self.reachable(dest):
                self.send(dest, key, payload, reliable=reliable)  # best effort: no path, no error

    def unwrap(self, key: str, payload: bytes) -> tuple[str, bytes] | None:
        """What arrived on ``key``, as its receiver handles it: the message itself, or, on our relay
        key, the relayed message when we are its end (None: passed on, refused as forged, or
        garbled, each counted)."""
        if key != self.keys.node_relay(self.node):
            return key, payload
        try:
            return self.on_relay(payload)
        except ProtocolError as exc:
            self._count("garbled", f"on {key}: {exc}")
            return None

    def on_relay(self, payload: bytes) -> tuple[str, bytes] | None:
        """A `Relayed` addressed to us: pass it on, or return (key, payload) if we are its end."""
        msg = decode(payload, Relayed)
        if msg.path[msg.hop] != self.node:
            raise ProtocolError(f"relay for {msg.path[msg.hop]} reached {self.node}")
        if msg.hop == len(msg.path) - 1:
            origin = msg.path[0]
            if self.signing is not None and not self.signing.check(msg, origin, f"a relayed {msg.key}", hop=1):
                self._count("forged", f"a relayed {msg.key} not signed by its origin {origin} (via {msg.path[-2]})")
                return None
            if self.access is not None and not self.access.may_put(origin, msg.key):
                # Zenoh's access control saw only the relay key; the inner key gets the same rule
                self._count("forged", f"{origin} may not put on {msg.key} (relayed via {msg.path[-2]})")
                return None
            if self._shuns(origin):
                self.direct.discard(origin)
                self.shunned.add(origin)
            return msg.key, msg.payload
        nxt = msg.path[msg.hop + 1]
        if nxt not in self.direct:  # the planned next hop is gone; the origin resends what matters
            self._count("relay-next-hop-gone", f"{nxt} on the way to {msg.path[-1]}")
            return None
        # forwarded as it came (its signature included): only the destination verifies it
        self.bus.publish(self.keys.node_relay(nxt), encode(dataclasses.replace(msg, hop=msg.hop + 1)))
        self.forwarded += 1
        return None
