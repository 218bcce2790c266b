"""Who may publish what: the team's access policy, one definition for Zenoh and for the processes.

Identities are certificate common names: the base station's node name, each robot's name, and
`OPERATOR` for the operator's CLI. Default deny: an identity may put only on the keys listed
here. Zenoh enforces this on every node that accepts connections (`runtime.access_control`
turns it into Zenoh's ``access_control`` section); the processes apply the same rules to what
Zenoh cannot see, such as the claimed origin of a relayed message and the node a status names.
"""

from __future__ import annotations

from dataclasses import dataclass

from autopower.protocol.codec import message_kind
from autopower.protocol.keys import Keys, key_matches
from autopower.protocol.messages import PeerStatus

OPERATOR = "operator"  # the operator CLI's identity (certificate CN)


@dataclass(frozen=True)
class TeamAccess:
    """The access policy of one team: its key space, base station, robots."""

    keys: Keys
    basestation: str
    robots: tuple[str, ...]

    @property
    def members(self) -> tuple[str, ...]:
        return (self.basestation, *self.robots)

    def puts(self, identity: str) -> tuple[str, ...]:
        """Key expressions ``identity`` may put on (empty for strangers and the operator)."""
        k = self.keys
        shared = (f"{k.prefix}/node/*/data", f"{k.prefix}/node/*/relay")
        if identity == self.basestation:
            # plans and migration orders come from the base station alone
            # (no `peer/<itself>`: each robot gets its view addressed to it, `basestation.peer_view`)
            return (k.plan, f"{k.prefix}/node/*/control", k.status(identity), k.addressed_by(identity), k.inbox, *shared)
        if identity in self.robots:
            # its own status and acknowledgements, outputs/frames, relays, inbox reports, subgroup rounds
            return (k.status(identity), k.peer(identity), k.addressed_by(identity), k.inbox, k.subgroup, *shared)
        return ()

    def liveliness(self, identity: str) -> tuple[str, ...]:
        return (self.keys.alive(identity),) if identity in self.members else ()

    def may_put(self, identity: str, key: str) -> bool:
        return any(key_matches(expr, key) for expr in self.puts(identity))

    def may_query_operator(self, identity: str) -> bool:
        return identity == OPERATOR


MAX_CLOCK_AHEAD_S = 5.0  # a status stamped further in the future is not believed (hosts run NTP)


def status_problem(keys: Keys, key: str, node: str, t_unix: float, now_unix: float) -> str | None:
    """Why a status read from ``key`` must be dropped, or None.

    Zenoh's access control only lets robot r put on ``status/r``; the status must then also name
    r (a robot cannot speak for another through its own key), and must not be stamped in the
    future: statuses are ordered by ``t_unix``, so one forged far ahead would mask every real one.
    """
    # a `NodeStatus`, a `PeerStatus`, or the base station's `PeerStatus` addressed to one robot
    owner = keys.node_of_status(key) or keys.node_of_peer(key) or (keys.addressed_ends(key) or (None, None))[1]
    return _report_problem("status", owner, node, t_unix, now_unix)


def carries_peer_status(keys: Keys, key: str, payload: bytes, me: str) -> bool:
    """Whether ``payload`` read from ``key`` is a status ``me`` acts on as a peer's: a robot's on
    ``peer/<r>``, or the base station's view addressed to ``me`` (``node/<me>/from/<base>``, where
    acks travel too: the kind tells them apart)."""
    if keys.node_of_peer(key) is not None:
        return True
    ends = keys.addressed_ends(key)
    return ends is not None and ends[0] == me and message_kind(payload) == PeerStatus.KIND


def addressed_problem(keys: Keys, key: str, node: str, t_unix: float, now_unix: float) -> str | None:
    """Why a message addressed to one node (an `Ack`, the base station's `PeerStatus` for it) read
    from ``key`` must be dropped, or None: the rules of `status_problem` (robot r may only put on
    ``node/*/from/r``, and the message must name r)."""
    ends = keys.addressed_ends(key)
    return _report_problem("addressed message", ends[1] if ends else None, node, t_unix, now_unix)


def _report_problem(what: str, owner: str | None, node: str, t_unix: float, now_unix: float) -> str | None:
    if owner != node:
        return f"a {what} naming {node!r} on {owner!r}'s key"
    if t_unix > now_unix + MAX_CLOCK_AHEAD_S:
        return f"{node}'s {what} is stamped {t_unix - now_unix:.0f} s in the future"
    return None
