"""Listening: what a base station hears of the team before it runs the mission (`takeover.py`).

A base station that comes up decides nothing until it knows whether the team already runs a
mission: it keeps each robot's status (`heard`), when each robot came into sight, and when it came
up itself. The mission starts, or the running one is adopted, once every robot in sight has
spoken or had the time to (``learn_team_s`` from when it came into sight), or once every robot of
the scenario has spoken or ``learn_team_s`` has passed since this base station came up.
"""

from __future__ import annotations

from collections.abc import Iterable, Set

from autopower.protocol import NodeStatus


class TeamListening:
    """The base station's listening before the mission. It owns the statuses heard and when each
    robot came into sight; the coordinator tells it who is in sight and gives it the time."""

    def __init__(self, *, up_unix: float, learn_team_s: float):
        self.up_unix = up_unix  # when this base station came up
        self.learn_team_s = learn_team_s
        self.heard: dict[str, NodeStatus] = {}  # robot -> its status before we run the mission
        self.first_seen_unix: float | None = None  # when the first robot came into sight
        self.seen_unix: dict[str, float] = {}  # robot -> when it last came into sight (it must speak before we decide)

    def heard_from(self, status: NodeStatus) -> None:
        self.heard[status.node] = status

    def came_into_sight(self, robot: str, now: float) -> None:
        self.seen_unix[robot] = now
        if self.first_seen_unix is None:
            self.first_seen_unix = now

    def running_reports(self, alive: Set[str]) -> dict[str, NodeStatus]:
        """The statuses of robots in sight that run a mission (a plan and its clock). A robot names
        its mission only to a base station that does not run its plan (`NodeRuntime.status`): until
        this one's status reaches it, it runs one without saying which, and none may start."""
        return {n: s for n, s in self.heard.items() if n in alive and s.plan_epoch >= 0}

    def listened_enough(self, robots: Iterable[str], now: float) -> bool:
        """Every robot of the scenario has spoken, or we listened for ``learn_team_s``."""
        return set(robots) <= set(self.heard) or now - self.up_unix >= self.learn_team_s

    def team_known(self, in_sight: Iterable[str], now: float) -> bool:
        """Enough is known to decide: every robot in sight has spoken, or had the time to since it
        came into sight. Counted per robot: a robot that comes into sight late may be the one that
        still runs the mission (the others restarted while this base station was down, and know
        none). Timed from the first robot seen, such a robot would never be waited for, and a second
        mission would start beside the running one."""
        return all(r in self.heard or now - self.seen_unix.get(r, now) >= self.learn_team_s for r in in_sight)

    def takeover_due(self, alive: Set[str], robots: Iterable[str], now: float) -> bool:
        """A robot in sight runs a mission, and we have listened enough to adopt it."""
        reports = self.running_reports(alive).values()
        return any(s.mission is not None for s in reports) and self.listened_enough(robots, now)

    def deadlines(self, alive: Set[str], robots: Iterable[str], in_sight: Iterable[str], now: float) -> list[float]:
        """When listening is done, ahead of ``now`` (a deadline in the past would spin the loop)."""
        out = []
        if self.running_reports(alive) and not self.listened_enough(robots, now):
            out.append(self.up_unix + self.learn_team_s)
        out += [self.seen_unix.get(r, self.first_seen_unix) + self.learn_team_s
                for r in in_sight if r not in self.heard]
        return [t for t in out if t > now]
