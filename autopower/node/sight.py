"""Sight: the nodes this one sees, and what it heard of the base station.

`Sight` is a collaborator of `NodeRuntime`. It owns the nodes in sight now (their liveliness tokens)
and every member of the team seen so far, with the scenario's links of this node (the status's
``links``: a link that went down must be seen coming back, one that never came up must be reported
down), and, from the base station's statuses, whether it runs this node's plan (else this node's
statuses carry the mission, for a base station that takes over) and whether one that runs no plan
yet began listening (the process then sends a status at once).
"""

from __future__ import annotations

from autopower.protocol import NodeStatus, PeerStatus


class Sight:
    """Who this node sees, and whether its statuses must name the mission."""

    def __init__(self, rt, *, link_ends: set[str] | frozenset[str], team: frozenset[str]):
        """``rt``: the `NodeRuntime` whose sight this is; ``link_ends``: the nodes it has a link with in
        the scenario; ``team``: the scenario's nodes."""
        self.rt = rt
        self.alive: set[str] = set()
        self._ever_alive: set[str] = set()  # every node whose token this one has seen (status `links`)
        # wall: until when a base station's status said it runs our plan, and one said it does not
        self._base_runs_our_plan_until = 0.0
        self._mission_wanted_until = 0.0
        self._status_asked = False  # a base station listening for the team asked: `take_status_asked`
        self._link_ends = link_ends  # the scenario's links of this node
        self._team = team

    def heard_basestation(self, status: NodeStatus | PeerStatus) -> None:
        """A base station's status: whether it runs the plan this node runs."""
        # for three periods it announced: one that stops talking may have restarted, and one that
        # runs another plan (or none: `PeerViews.listening`) may be a second base station beside
        # the first, which takes over only once a robot names the mission
        until = self.rt.wall() + 3 * max(status.next_status_s, 0.5)
        plan = self.rt.plan
        if plan is not None and status.plan_epoch == plan.epoch:
            self._base_runs_our_plan_until = until
        else:
            if status.plan_epoch < 0 and self.rt.wall() >= self._mission_wanted_until:
                self._status_asked = True  # a base station that runs nothing yet, newly heard
            self._mission_wanted_until = until

    def on_liveliness(self, node: str, alive: bool) -> None:
        if node == self.rt.scenario.basestation:
            self._base_runs_our_plan_until = 0.0  # gone, or a new process: the mission in our statuses
        if alive:
            self.alive.add(node)
            if node in self._team:  # a name from the network only grows this set if it is a member
                self._ever_alive.add(node)
        else:
            self.alive.discard(node)

    def links(self) -> dict[str, bool]:
        """The status's ``links``: whether each node this one has a link with in the scenario, or has
        ever seen, is in sight. Not every node of the team: a robot's status grew with the team (1.4 of
        its 2.5 kB at 100)."""
        others = sorted((self._link_ends | self._ever_alive) - {self.rt.node})
        return {n: n in self.alive for n in others}

    def take_status_asked(self) -> bool:
        """Whether a base station that runs no plan yet (`PeerViews.listening`: one taking over the
        team, or a second one) began listening since last asked. It learns the team from the
        statuses it hears within its listening window (`CoordinatorConfig.learn_team_s`), shorter
        than the heartbeat a robot with nothing new keeps: the process then sends one at once, or
        the takeover would go on without that robot's stages."""
        asked, self._status_asked = self._status_asked, False
        return asked

    def mission_wanted(self) -> bool:
        """Whether this node's status names its mission (`heard_basestation`)."""
        now = self.rt.wall()
        return now < self._mission_wanted_until or now >= self._base_runs_our_plan_until
