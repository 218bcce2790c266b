"""Who may publish what: the team's access policy, one definition for Zenoh and for the processes.

Identities are certificate common names: the base station's node name, each robot's name, and
`OPERATOR` for the operator's CLI. Default deny: an identity may put only on the keys listed
here. Zenoh enforces this on every node that accepts connections (`runtime.access_control`
turns it into Zenoh's ``access_control`` section); the processes apply the same rules to what
Zenoh cannot see, such as the claimed origin of a relayed message and the node a status names.
"""

from __future__ import annotations

from dataclasses import dataclass

from autopower.protocol.keys import Keys, key_matches

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
            return (k.plan, f"{k.prefix}/node/*/control", k.status(identity), k.inbox, *shared)
        if identity in self.robots:
            # its own status and outputs/frames, relays, inbox reports, subgroup rounds
            return (k.status(identity), k.inbox, k.subgroup, *shared)
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
    owner = keys.node_of_status(key)
    if owner != node:
        return f"a status naming {node!r} on {owner!r}'s key"
    if t_unix > now_unix + MAX_CLOCK_AHEAD_S:
        return f"{node}'s status is stamped {t_unix - now_unix:.0f} s in the future"
    return None
