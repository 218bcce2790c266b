"""What the team's own coordination costs each robot's radios: statuses and keep-alives on every link.

The paper charges chain messages only. A running team also sends, on every link it holds a session
on (a direct link of the network: Zenoh peers do not relay), its statuses and the transport's
keep-alives, and each of those small messages is acknowledged by the other end. Over 802.11a that
is a rounding error; over GSM it is a third of a robot's idle power (docs/concepts/energy-model.md).

Rules, per direct link u-v and per direction u -> v (the scenario's ``[control_plane]``):
- u sends one status a heartbeat (``heartbeat_s``): to a base station its status, whole
  (``status_bytes``) once every `KEYFRAME_EVERY_S` and as its change from that one
  (``status_change_bytes``) between (`status_mean_bytes`); to a robot the compact one robots read
  of each other (``peer_status_bytes``). A node
  says a change (a plan, a stage's state, a link) within a status period (``status_period_s``),
  but a team runs in its steady state: counts move, nothing changes (`runtime.cadence`).
- The transport sends a keep-alive (``keep_alive_bytes``) every lease / ``keep_alives_per_lease``
  in which it sent nothing else on that link: the keep-alives fill the intervals the statuses
  leave, so a link carries max(keep-alive rate, status rate) messages a second each way.
- Each of those messages travels in a packet of its own: ``packet_overhead_bytes`` more (IP and TCP
  headers and the TLS record around it), and the other end answers with an acknowledgement of
  ``ack_bytes`` (a message a status period apart is never coalesced into a delayed ACK).
- A robot with no direct link to the base station has its status relayed there along its
  route (Zenoh peers do not relay; the agents do), each copy with its route and signature
  (``relayed_extra_bytes``), acknowledged on every hop.
- Bytes become airtime on the link's medium with the link's loss (`model.energy.airtime_s`), paid
  at send_w by the sender and receive_w by the receiver, like a chain's message.

The loads are constant for a network (they do not depend on where stages run), so they enter the
evaluator once per load space (`LoadSpace.control`) and the MILP as constants on each link's media
terms (`planner.milp`). ``enabled = false`` (the default, and the paper's assumption) leaves every
figure as the paper's Fig. 7.

The lease is the failure detection time (a cut link or a dead peer is seen once its lease runs
out), and two heartbeats are (a peer whose loop is stuck while its session lives: the status-silence
detector, `node.peer_watch`), so a mission requirement ``max_detection_s`` fixes both: every term
above only falls with a longer lease or heartbeat, so the lifetime-optimal choice within the
requirement is the longest allowed (`ControlPlaneSpec.lease_for`, `heartbeat_for`), not a search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from autopower.errors import ScenarioError

# Measured on the runtime (the paper's team under `up`, fields by position: docs/concepts/energy-model.md):
# the status a robot sends to the base station whole (a keyframe: 754-771 B encoded) and as its change
# from the last whole one (at rest 218 B on average, running 310-329 B), and the one it sends robots
# (111-118 B), each with Zenoh's put and key.
DEFAULT_STATUS_BYTES = 800
DEFAULT_STATUS_CHANGE_BYTES = 250
DEFAULT_PEER_STATUS_BYTES = 150
# A node's status goes whole at least this often, as its change from the last whole one between
# (`protocol.statuses.KEY_EVERY_S`: the model cannot import the protocol; a test checks they agree).
KEYFRAME_EVERY_S = 10.0
# A Zenoh keep-alive: its message and the stream's length prefix.
DEFAULT_KEEP_ALIVE_BYTES = 8
# IPv4 (20) + TCP with timestamps (32) + a TLS 1.3 record (22) around each small message.
DEFAULT_PACKET_OVERHEAD_BYTES = 74
DEFAULT_ACK_BYTES = 52  # an empty TCP segment with timestamps
# A relayed message's envelope: its route and the sender's signature (measured: +517 B).
DEFAULT_RELAYED_EXTRA_BYTES = 517
# Heartbeats a peer may miss before the status-silence detector takes it for gone (`WatchSettings.periods`).
SILENT_HEARTBEATS = 2


@dataclass(frozen=True, kw_only=True)
class ControlPlaneSpec:
    """The scenario's ``[control_plane]``: whether the team's own messages are charged, and their shape."""

    enabled: bool = False
    status_period_s: float = 0.5  # a change is said within this (the runtime's tick); not charged
    heartbeat_s: float = 2.0  # a status with nothing new in it, this often: what a steady team sends
    lease_s: float = 0.5
    keep_alives_per_lease: int = 2
    status_bytes: int = DEFAULT_STATUS_BYTES
    status_change_bytes: int = DEFAULT_STATUS_CHANGE_BYTES
    peer_status_bytes: int = DEFAULT_PEER_STATUS_BYTES
    keep_alive_bytes: int = DEFAULT_KEEP_ALIVE_BYTES
    packet_overhead_bytes: int = DEFAULT_PACKET_OVERHEAD_BYTES
    ack_bytes: int = DEFAULT_ACK_BYTES
    relayed_extra_bytes: int = DEFAULT_RELAYED_EXTRA_BYTES
    max_detection_s: float | None = None  # the mission's requirement: a failure seen within this

    def __post_init__(self) -> None:
        if self.status_period_s <= 0 or self.lease_s <= 0 or self.keep_alives_per_lease < 1:
            raise ScenarioError("control_plane: status_period_s and lease_s must be > 0 and "
                                "keep_alives_per_lease >= 1")
        if self.max_detection_s is not None and SILENT_HEARTBEATS * self.heartbeat_s > self.max_detection_s:
            raise ScenarioError(f"control_plane: heartbeat_s {self.heartbeat_s:g} is longer than half of "
                                f"max_detection_s {self.max_detection_s:g}: a peer whose loop is stuck is found "
                                f"after two heartbeats; give a heartbeat_s <= {self.max_detection_s / 2:g} or "
                                "leave it out to have it chosen")
        if self.heartbeat_s < self.status_period_s:
            raise ScenarioError(f"control_plane: heartbeat_s {self.heartbeat_s:g} is shorter than status_period_s "
                                f"{self.status_period_s:g}: a status goes out at most once a status period; "
                                f"give a heartbeat_s >= {self.status_period_s:g}")
        if self.max_detection_s is not None and self.lease_s > self.max_detection_s:
            raise ScenarioError(f"control_plane: lease_s {self.lease_s:g} is longer than max_detection_s "
                                f"{self.max_detection_s:g}: a failure would be seen too late; give a "
                                f"lease_s <= {self.max_detection_s:g} or leave lease_s out to have it chosen")

    @staticmethod
    def lease_for(max_detection_s: float, choices_s: tuple[float, ...] = (0.5, 1.0, 2.0, 5.0, 10.0)) -> float:
        """The longest lease that still sees a failure within ``max_detection_s``: every control
        cost falls as the lease grows, so nothing shorter can give a longer lifetime."""
        allowed = [c for c in choices_s if c <= max_detection_s]
        if not allowed:
            raise ScenarioError(f"control_plane: max_detection_s {max_detection_s:g} is shorter than the "
                                f"shortest lease chosen from ({min(choices_s):g} s); give lease_s yourself "
                                f"(at least 0.1 s) or a longer requirement")
        return max(allowed)

    @staticmethod
    def heartbeat_for(max_detection_s: float, status_period_s: float = 0.5) -> float:
        """The longest heartbeat whose silence (`SILENT_HEARTBEATS` of them) still shows a stuck
        peer within ``max_detection_s``, never shorter than the status period."""
        return max(status_period_s, max_detection_s / SILENT_HEARTBEATS)

    def messages_per_s(self) -> float:
        """Messages each way on one link a second: statuses, and keep-alives where none went."""
        return max(self.keep_alives_per_lease / self.lease_s, 1.0 / self.heartbeat_s)

    def status_mean_bytes(self) -> float:
        """A status to a base station on average, one a heartbeat: whole at the first heartbeat at
        least `KEYFRAME_EVERY_S` after the last whole one, as its change from it in between."""
        per_keyframe = max(1, math.ceil(KEYFRAME_EVERY_S / self.heartbeat_s - 1e-9))
        return (self.status_bytes + (per_keyframe - 1) * self.status_change_bytes) / per_keyframe

    def own_bytes_per_s(self, to_basestation: bool) -> float:
        """Bytes a second a node puts on its link to a neighbour of its own: its status (the whole
        one or its change to a base station, the short one to a robot) and keep-alives in the
        intervals left."""
        status_rate = 1.0 / self.heartbeat_s
        keep_alive_rate = self.messages_per_s() - status_rate
        status = self.status_mean_bytes() if to_basestation else self.peer_status_bytes
        return (status_rate * (status + self.packet_overhead_bytes)
                + keep_alive_rate * (self.keep_alive_bytes + self.packet_overhead_bytes))

    def directed_bytes(self, network: Any) -> dict[tuple[str, str], float]:
        """(u, v) -> bytes a second u sends v on their direct link of ``network`` (a `model.network.Network`:
        not imported, the scenario holds this spec and the network module imports the scenario).

        Each end's own messages and its acknowledgements of the other's; and a robot with no direct
        link to the base station has its status carried there hop by hop, each relayed copy signed
        (``relayed_extra_bytes``) and acknowledged on every hop."""
        base = network.basestation
        out: dict[tuple[str, str], float] = {}
        for link in network.links:
            for u, v in ((link.a, link.b), (link.b, link.a)):
                out[u, v] = (out.get((u, v), 0.0) + self.own_bytes_per_s(to_basestation=v == base)
                             + self.messages_per_s() * self.ack_bytes)
        status_rate = 1.0 / self.heartbeat_s
        for robot in network.nodes:
            if robot == base or base in network.neighbours(robot) or not network.reachable(robot, base):
                continue
            for u, v, _ in network.route(robot, base):
                relayed = self.status_mean_bytes() + self.relayed_extra_bytes + self.packet_overhead_bytes
                out[u, v] = out.get((u, v), 0.0) + status_rate * relayed
                out[v, u] = out.get((v, u), 0.0) + status_rate * self.ack_bytes
        return out


OFF = ControlPlaneSpec()
