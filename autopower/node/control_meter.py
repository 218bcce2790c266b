"""The control plane's bytes on a node's links: everything its session exchanges with a peer beyond
the chains' own packets, to be charged to the radio of that link as the ``control`` part.

Rule: control = what crossed the link (`runtime.link_traffic`, per peer session) minus the chain
packets this node put on it or took from it (frames, migrated state, resends: counted here as
their encoded size, `note_data`). So Zenoh's and TCP's framing of the chain packets is control
too: the model's message sizes do not include it.

Both counts only grow, but not in step: a packet is counted here when it is published and by the
kernel when it leaves. The control bytes charged are therefore ``max(0, link - data)`` so far,
less what was charged before: never negative, and never charged twice.

A peer session is named by the Zenoh id its node announces in its status (`learn_zid`): a node
may only publish its own status (access control), and an id claimed by two nodes is attributed
to neither (counted as ``conflicts``).
"""

from __future__ import annotations

import re
from typing import Callable, Mapping

ZID = re.compile(r"[0-9a-f]{1,32}")  # a Zenoh id as its admin space spells it
MAX_SESSIONS = 4096  # peer sessions remembered (each restart of a peer is a new one): memory stays bounded

Direction = str  # "send" | "receive"


class ControlPlaneMeter:
    """Per peer node: chain bytes noted, link bytes measured, control bytes charged."""

    def __init__(self) -> None:
        self._node_of_zid: dict[str, str] = {}
        self._conflicting: set[str] = set()
        self.conflicts = 0
        self.data: dict[tuple[str, Direction], int] = {}  # (peer, direction) -> chain packets' bytes
        self.link: dict[tuple[str, Direction], int] = {}  # (peer, direction) -> all bytes, measured
        self.charged: dict[tuple[str, Direction], int] = {}  # (peer, direction) -> control bytes charged
        # the totals when counting started (`start_from`): what came before is not this mission's
        self._link_at_start: dict[tuple[str, Direction], int] = {}
        self._control_at_start: dict[tuple[str, Direction], int] = {}
        self.packets: dict[tuple[str, Direction], int] = {}  # (peer, direction) -> TCP segments, measured
        self._packets_at_start: dict[tuple[str, Direction], int] = {}

    # ---- what the node learns ---------------------------------------------------------------------
    def learn_zid(self, node: str, zid: str) -> bool:
        """``node`` says its session is ``zid``; False (ignored) if it is not a Zenoh id or another
        node claims it too."""
        if not ZID.fullmatch(zid) or zid in self._conflicting:
            return False
        known = self._node_of_zid.get(zid)
        if known is not None and known != node:
            self._conflicting.add(zid)
            del self._node_of_zid[zid]
            self.conflicts += 1
            return False
        if known is None and len(self._node_of_zid) >= MAX_SESSIONS:
            return False
        # a restarted node has a new session; its old one stays its own (the bytes it carried count)
        self._node_of_zid[zid] = node
        return True

    def note_data(self, peer: str, direction: Direction, n_bytes: int) -> None:
        """A chain packet of ``n_bytes`` (encoded) sent to or received from ``peer``."""
        key = (peer, direction)
        self.data[key] = self.data.get(key, 0) + n_bytes

    # ---- charging ---------------------------------------------------------------------------------
    def measure(self, by_zid: Mapping[str, tuple[int, int]]) -> list[tuple[str, Direction, int]]:
        """The link totals per peer session so far (`LinkTraffic.poll`): the control bytes not yet
        charged, as (peer node, direction, bytes). Sessions no status names yet wait (their
        totals are kept by the caller, so nothing is lost by waiting)."""
        due = []
        for key, total in self._by_node(by_zid).items():
            self.link[key] = max(self.link.get(key, 0), total)
            control = max(0, self.link[key] - self.data.get(key, 0))
            grew = control - self.charged.get(key, 0)
            if grew > 0:
                self.charged[key] = control
                due.append((key[0], key[1], grew))
        return due

    def count_packets(self, by_zid: Mapping[str, tuple[int, int]]) -> None:
        """The segments each peer session exchanged so far (`LinkTraffic.packets_by_peer`): what a
        radio carries as packets, whatever their size (reported, not priced: the bytes are)."""
        for key, total in self._by_node(by_zid).items():
            self.packets[key] = max(self.packets.get(key, 0), total)

    def _by_node(self, by_zid: Mapping[str, tuple[int, int]]) -> dict[tuple[str, Direction], int]:
        """Per-session (sent, received) totals summed per (peer node, direction): the sessions a
        status names only (a restarted node's old and new sessions add up)."""
        totals: dict[tuple[str, Direction], int] = {}
        for zid, (sent, received) in by_zid.items():
            node = self._node_of_zid.get(zid)
            if node is not None:
                for direction, n in (("send", sent), ("receive", received)):
                    totals[(node, direction)] = totals.get((node, direction), 0) + n
        return totals

    def start_from(self, by_zid: Mapping[str, tuple[int, int]],
                   packets_by_zid: Mapping[str, tuple[int, int]] | None = None) -> None:
        """Counting starts here: these totals (before the mission) are neither charged nor reported."""
        self.measure(by_zid)
        self.count_packets(packets_by_zid or {})
        self._link_at_start, self._control_at_start = dict(self.link), dict(self.charged)
        self._packets_at_start = dict(self.packets)

    def charge(self, by_zid: Mapping[str, tuple[int, int]], meter, medium_to: Callable[[str], str | None],
               t: float) -> int:
        """Charge the control bytes due (`measure`) to ``meter``, each on the radio of its link
        (``medium_to(peer)``) at virtual time ``t``: the ``<medium>:control`` part. The bytes of a
        link with no known medium are not priced; their count is returned."""
        unpriced = 0
        for peer, direction, n in self.measure(by_zid):
            medium = medium_to(peer)
            if medium is None:
                unpriced += n
                continue
            # the kernel's count has every retransmission in it already: priced as a lossless link
            meter.charge_radio(direction, medium, n, 1.0, t, purpose="control")
        return unpriced

    # ---- readings ---------------------------------------------------------------------------------
    def link_bytes(self) -> tuple[int, int]:
        """(sent, received) on every link since counting started, as measured."""
        return _by_direction(self.link, self._link_at_start)

    def link_packets(self) -> tuple[int, int]:
        """(sent, received) TCP segments on every link since counting started, as measured."""
        return _by_direction(self.packets, self._packets_at_start)

    def control_bytes(self) -> tuple[int, int]:
        """(sent, received) of the control plane since counting started (what was charged)."""
        return _by_direction(self.charged, self._control_at_start)


def _by_direction(totals: Mapping[tuple[str, Direction], int], start: Mapping[tuple[str, Direction], int]
                  ) -> tuple[int, int]:
    return (sum(n - start.get(k, 0) for k, n in totals.items() if k[1] == "send"),
            sum(n - start.get(k, 0) for k, n in totals.items() if k[1] == "receive"))
