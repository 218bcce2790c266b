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
        head = f"{self.prefix}/alive/"
        if key.startswith(head) and "/" not in key[len(head):]:
            return key[len(head):]
        return None

    # telemetry
    def status(self, node: str) -> str:
        return f"{self.prefix}/status/{check_name(node, 'node')}"

    @cached_property
    def status_all(self) -> str:
        return f"{self.prefix}/status/*"

    def node_of_status(self, key: str) -> str | None:
        head = f"{self.prefix}/status/"
        if key.startswith(head) and "/" not in key[len(head):]:
            return key[len(head):]
        return None

    # coordinator
    @cached_property
    def plan(self) -> str:
        return f"{self.prefix}/base/plan"

    @cached_property
    def inbox(self) -> str:
        return f"{self.prefix}/base/inbox"

    @cached_property
    def operator(self) -> str:
        return f"{self.prefix}/base/operator"

    def all_keys_of(self, node: str, basestation: bool) -> list[str]:
        """The keys a node subscribes to (used by the garbage-survival tests)."""
        keys = [self.node_data(node), self.node_control(node), self.plan, self.status_all]
        if basestation:
            keys += [self.inbox, self.operator]
        return keys
