"""Every Zenoh key expression AutoPower uses; no other module builds key strings.

All keys live under ``autopower/<team>/`` so that several teams (or parallel test runs) never
see each other's traffic even on a shared network.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cached_property

ROOT = "autopower"
_NAME = re.compile(r"^[A-Za-z0-9_.+-]+$")  # a key chunk: no '/', '*', '$', '?', '#'
_MEMO_KEYS = 1024  # node keys a `Keys` remembers (names from the network must not grow it without bound)
_MEMO_NAME_CHARS = 64


def check_name(name: str, what: str = "name") -> str:
    if not isinstance(name, str) or not _NAME.match(name):
        raise ValueError(f"{what} {name!r} cannot be used in a key expression "
                         "(letters, digits and _ . + - only)")
    return name


def key_matches(pattern: str, key: str) -> bool:
    """Whether a concrete key matches a key expression with ``*`` and ``**`` chunks."""
    p, k = pattern.split("/"), key.split("/")

    def go(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(go(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return (p[i] == "*" or p[i] == k[j]) and go(i + 1, j + 1)

    return go(0, 0)


def carries_chain_data(key: str, reliable: bool) -> bool:
    """Whether a message on ``key`` is the data plane: chain frames (``node/<n>/data``) and the
    reliable messages relays carry on (``node/<n>/relay``, mostly frames; packets a relay forwards
    keep their order, which Zenoh keeps only within one priority).

    The rest (statuses, acks, plans, migrations, subgroup rounds) is the control plane, which a
    transport should put ahead of the data: a radio saturated by frames must still carry the
    statuses that say who is there and the acks that free the producers' buffers.
    """
    if not key.startswith(f"{ROOT}/"):
        return False
    tail = key.rsplit("/", 2)
    return len(tail) == 3 and tail[0].endswith("/node") and (tail[2] == "data" or (tail[2] == "relay" and reliable))


@dataclass(frozen=True)
class Keys:
    """Key expressions of one team."""

    team: str

    def __post_init__(self) -> None:
        check_name(self.team, "team")

    @cached_property
    def prefix(self) -> str:
        return f"{ROOT}/{self.team}"

    def _node_key(self, node: str, what: str) -> str:
        # asked for every message a node sends or takes in: each node's keys are built (and its
        # name checked) once; a team has a handful of nodes, so a few names are remembered
        memo = self.__dict__.setdefault("_node_keys", {})
        key = memo.get((node, what))
        if key is None:
            key = f"{self.prefix}/node/{check_name(node, 'node')}/{what}"
            if len(memo) < _MEMO_KEYS and len(node) <= _MEMO_NAME_CHARS:
                memo[(node, what)] = key
        return key

    # data and control addressed to one node (robot agent or the base station's host)
    def node_data(self, node: str) -> str:
        return self._node_key(node, "data")

    def node_control(self, node: str) -> str:
        return self._node_key(node, "control")

    def node_relay(self, node: str) -> str:
        """Control-plane messages another node asks this one to carry on (`Relayed`)."""
        return self._node_key(node, "relay")

    def node_all(self, node: str) -> str:
        """Everything for ``node``: its data, control and relay keys and what others address to it
        (`addressed_to`). A node takes them on one subscription: each subscription is a thread of its
        process that wakes ten times a second at rest (`runtime.bus._Pump`) and a declaration every
        peer keeps."""
        return f"{self.prefix}/node/{check_name(node, 'node')}/**"

    @cached_property
    def subgroup(self) -> str:
        """Subgroup agreement rounds among robots (propose, votes, decision)."""
        return f"{self.prefix}/subgroup"

    # presence
    def alive(self, node: str) -> str:
        return f"{self.prefix}/alive/{check_name(node, 'node')}"

    @cached_property
    def alive_all(self) -> str:
        return f"{self.prefix}/alive/*"

    def node_of_alive(self, key: str) -> str | None:
        return self._node_after("alive", key)

    # telemetry
    def status(self, node: str) -> str:
        return f"{self.prefix}/status/{check_name(node, 'node')}"

    @cached_property
    def status_all(self) -> str:
        return f"{self.prefix}/status/*"

    def node_of_status(self, key: str) -> str | None:
        return self._node_after("status", key)

    # what a robot needs of each peer's status (`PeerStatus`): the robots subscribe to these only
    def peer(self, node: str) -> str:
        return f"{self.prefix}/peer/{check_name(node, 'node')}"

    @cached_property
    def peer_all(self) -> str:
        return f"{self.prefix}/peer/*"

    def node_of_peer(self, key: str) -> str | None:
        return self._node_after("peer", key)

    def _node_after(self, what: str, key: str) -> str | None:
        """The node a ``<prefix>/<what>/<node>`` key names (None for any other key)."""
        head = f"{self.prefix}/{what}/"
        if key.startswith(head) and "/" not in key[len(head):]:
            return key[len(head):]
        return None

    # messages one node addresses to another, in its own name: acknowledgements (what it consumed
    # of the frames the other sent it) and the base station's `PeerStatus` as one robot needs it
    def addressed(self, to: str, node: str) -> str:
        return f"{self._node_key(to, 'from')}/{check_name(node, 'node')}"

    def addressed_to(self, node: str) -> str:
        """What is addressed to ``node``: what it subscribes to."""
        return f"{self._node_key(node, 'from')}/*"

    def addressed_by(self, node: str) -> str:
        """What ``node`` may put: messages to anyone, in its own name."""
        return f"{self.prefix}/node/*/from/{check_name(node, 'node')}"

    def addressed_ends(self, key: str) -> tuple[str, str] | None:
        """(to, from) of an addressed message's key; None for any other key."""
        head = f"{self.prefix}/node/"
        if not key.startswith(head):
            return None
        parts = key[len(head):].split("/")
        if len(parts) != 3 or parts[1] != "from" or not _NAME.match(parts[0]) or not _NAME.match(parts[2]):
            return None
        return parts[0], parts[2]

    # coordinator
    @cached_property
    def plan(self) -> str:
        return f"{self.prefix}/base/plan"

    @cached_property
    def inbox(self) -> str:
        return f"{self.prefix}/base/inbox"

    @cached_property
    def base_all(self) -> str:
        """The plans and the inbox on one subscription (`node_all`: why); the operator's key is a
        queryable's, which no put reaches."""
        return f"{self.prefix}/base/*"

    @cached_property
    def operator(self) -> str:
        return f"{self.prefix}/base/operator"

    def all_keys_of(self, node: str, basestation: bool) -> list[str]:
        """The keys a node subscribes to (used by the garbage-survival tests)."""
        keys = [self.node_data(node), self.node_control(node), self.addressed_to(node),
                self.status_all if basestation else self.peer_all]
        if basestation:
            keys += [self.plan, self.inbox, self.operator]  # a robot's plans come on its control key
        return keys
