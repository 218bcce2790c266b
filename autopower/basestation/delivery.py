"""Delivering plans: which robot gets a new plan when, whole or as its change from the plan it holds.

A robot gets its plans on its own control key (relayed when out of sight, `Relayer.send`); the plan
key carries every plan to base stations and recorders (`PlanPublisher.publish_plan`). What each
robot in reach gets of a new plan:

- whole: the first plan of this base station (or of a new mission), and a robot that was not in
  reach when the plan before went out or was never sent one;
- at once, as its change from the plan last sent to it: a robot the new plan concerns (it changes a
  stage, run or predicted power of a chain the robot sources, sinks or hosts a stage of, before,
  now or in the target; its own predicted power; a route of its to a node of one of those chains,
  or its radios' links; or the levels, variants or the operator's settings, which every robot acts
  on; every change when a chain is fed by another's flow);
- later, every other robot, as one change from the plan it holds: when no order waits for its
  answer (the wave of moves is over) or `plan_catch_up_s` after the first plan it was not sent.

A robot's plan is thus the base station's newest in all it acts on, and the base station takes a
robot for running a plan when it runs the last one sent to it (`holds`): for resends
(`PlanPublisher.behind_plan`), a fault's reconfiguration (`TeamFaults.mark_reconfigured`) and
battery drift (`Deciding.check_drift`).

What a robot is sent of a plan is its part (`robot_part`, protocol 8): the plan with the robot's own
predicted power alone, the only one it acts on. A new decision predicts every robot's power anew,
so a change that carried the team's predicted power grew with the team; a robot's part changes by
its own figure. Every part of one plan shares the hash of all but the predicted power
(`shared_digest`), made once per plan; a robot's change is the plan's change (made once per base
epoch) with the robot's predicted power and the digests of its parts (`_change_for`).
"""

from __future__ import annotations

import dataclasses
from collections import deque

from autopower.model.network import Link, Network
from autopower.protocol import LinkInfo, NodeStatus, PlanChange, PlanUpdate, encode
from autopower.protocol.plans import part_digest, plan_change, robot_part, shared_digest

PLAN_HISTORY = 64  # plans kept to make a robot holding an older one its change (`PlanDelivery.history`)


class PlanDelivery:
    """The plans' way to each robot: what was sent to whom, who waits for the newest, and when it goes."""

    def __init__(self, team):
        """``team``: the `Coordinator` whose robots, statuses, placement and ways out a delivery uses."""
        self.team = team
        self.sent: dict[str, tuple[int, int]] = {}  # robot -> (incarnation, epoch) of the plan last sent to it
        self.sent_epochs: dict[str, deque[int]] = {}  # robot -> the epochs of this incarnation sent to it
        # our plans of this series (incarnation, mission, leader) by epoch, as the robots decode them, with
        # their digests: what a change to a robot holding an older one starts from
        self.history: dict[int, tuple[PlanUpdate, bytes]] = {}
        self.lagging: set[str] = set()  # robots in reach holding an older plan than the newest
        self.catch_up_unix: float | None = None  # when they get the newest, whatever it changes
        self.reached: set[str] = set()  # the robots in reach when the last new plan went out
        self.last_concerned: set[str] | None = None  # whom the last new change concerned (None: everyone)
        self._shared: dict[int, bytes] = {}  # epoch -> `shared_digest` of our plan of it (a part's hash starts from it)
        self._chains_by_name = {c.name: c for c in team.scenario.chains}
        self._has_flows = any(c.inputs for c in team.scenario.chains)  # a flow feeds a stage from another chain

    # ---- what robots hold ----------------------------------------------------------------------------------
    def needed(self, robot: str, epoch: int) -> int:
        """The epoch of our plans that ``robot`` must run to run ``epoch`` as far as it concerns it: the
        last one sent to it up to ``epoch`` (a plan that changes nothing it acts on is sent later);
        ``epoch`` itself when none is known."""
        sent = self.sent_epochs.get(robot)
        if not sent or sent[0] > epoch:
            return epoch
        return max(e for e in sent if e <= epoch)

    def holds(self, status: NodeStatus, epoch: int) -> bool:
        """Does the node run our plan of ``epoch`` as far as it concerns it (`needed`)?"""
        return self.team.runs_plan(status, self.needed(status.node, epoch), newer=True)

    def remember(self, update: PlanUpdate, digest: bytes, continues: bool) -> None:
        """A new plan (``digest``: of its whole form), the next of our series when ``continues``, else
        the first of a new one (the robots get it whole)."""
        if not continues:
            self.history.clear()
            self._shared.clear()
        self.history[update.epoch] = (update, digest)
        self._shared.pop(update.epoch, None)
        while len(self.history) > PLAN_HISTORY:
            self._shared.pop(next(iter(self.history)), None)
            del self.history[next(iter(self.history))]

    # ---- sending -----------------------------------------------------------------------------------------------
    def deliver(self, update: PlanUpdate, payload: bytes, change: PlanChange | None) -> None:
        """The new plan ``update`` (``payload``: whole, or ``change`` from the plan before, as the plan key
        carries it) to the robots in reach, each its part (`robot_part`), by the module's rules."""
        team = self.team
        alive = team.alive_nodes()  # (a set built per call: once, not once per robot)
        in_reach = [r for r in team.robots if r in alive]
        if change is None:
            self.lagging.clear()
            self.catch_up_unix = None
            for robot in in_reach:
                self._send(robot, update, self._whole_for(robot, update))
            self.reached = set(in_reach)
            return
        concerned = self._concerned(change, update)
        self.last_concerned = concerned
        everyone = concerned is None or not team.placing.migrations  # (the wave is over: those behind catch up)
        made: dict[int, PlanChange] = {update.epoch - 1: change}  # the plan's change from each base epoch, made once
        for robot in in_reach:
            if robot not in self.reached:
                self._send(robot, update, self._whole_for(robot, update))  # back in reach: whole
            elif everyone or robot in concerned:
                self._send(robot, update, self._change_for(robot, update, made))
            else:
                self.lagging.add(robot)
        self.lagging &= set(in_reach)
        self.reached = set(in_reach)
        if not self.lagging:
            self.catch_up_unix = None
        elif self.catch_up_unix is None:
            self.catch_up_unix = team.wall() + team.config.plan_catch_up_s

    def catch_up_due(self, now_wall: float) -> bool:
        """Robots wait for the newest plan and their time is up (`catch_up`)."""
        return self.catch_up_unix is not None and now_wall >= self.catch_up_unix

    def catch_up(self, incarnation: int, epoch: int) -> None:
        """The robots holding an older plan than the newest, ours of (``incarnation``, ``epoch``), get
        it as their change from the one they hold."""
        lagging, self.lagging, self.catch_up_unix = self.lagging, set(), None
        team = self.team
        newest = self.history.get(epoch)
        if (team.mission is None or team.takeover.stepped_down is not None or newest is None
                or newest[0].incarnation != incarnation):
            return
        alive = team.alive_nodes()
        made: dict[int, PlanChange] = {}
        for robot in sorted(lagging):
            if robot in alive and robot in self.reached:
                self._send(robot, newest[0], self._change_for(robot, newest[0], made))

    def resend(self, robots: list[str], update: PlanUpdate, payload: bytes) -> None:
        """The current plan ``update`` again, whole (each robot's part: ``payload`` is the whole plan's), to ``robots``."""
        for robot in robots:
            self._send(robot, update, self._whole_for(robot, update))

    def _whole_for(self, robot: str, update: PlanUpdate) -> bytes:
        """``robot``'s part of ``update``, whole."""
        return encode(robot_part(update, robot))

    def _part_digest(self, update: PlanUpdate, robot: str) -> bytes:
        """`plan_digest` of ``robot``'s part of our plan ``update`` (kept in `history`), without hashing it whole."""
        shared = self._shared.get(update.epoch)
        if shared is None:
            shared = self._shared[update.epoch] = shared_digest(update)  # (history keeps sorted plans)
        return part_digest(shared, robot_part(update, robot).predicted_w)

    def _change_for(self, robot: str, update: PlanUpdate, made: dict[int, PlanChange]) -> bytes:
        """``update`` for ``robot``: the change of its part from the part last sent to it (whole if that
        plan is not kept). The plan's change from that plan is made once (``made``, by base epoch);
        the robot's part of it differs only in the predicted power and the digests."""
        sent = self.sent.get(robot)
        held = self.history.get(sent[1]) if sent is not None and sent[0] == update.incarnation else None
        if held is None or held[0].leader != update.leader or update.epoch not in self.history:
            return self._whole_for(robot, update)
        base = held[0]
        change = made.get(base.epoch)
        if change is None:
            change = made[base.epoch] = plan_change(base, held[1], update, self.history[update.epoch][1])
        old, new = base.predicted_w.get(robot), update.predicted_w.get(robot)
        return encode(dataclasses.replace(
            change, base_digest=self._part_digest(base, robot), digest=self._part_digest(update, robot),
            predicted_w={robot: new} if new is not None and new != old else {},
            not_predicted=(robot,) if old is not None and new is None else ()))

    def _send(self, robot: str, update: PlanUpdate, payload: bytes) -> None:
        team = self.team
        self.lagging.discard(robot)
        team.send_to(robot, team.keys.node_control(robot), payload)
        self.sent[robot] = (update.incarnation, update.epoch)
        sent = self.sent_epochs.get(robot)
        if sent is None or (sent and sent[-1] > update.epoch):  # (a new incarnation starts its epochs anew)
            sent = self.sent_epochs[robot] = deque(maxlen=PLAN_HISTORY)
        if not sent or sent[-1] != update.epoch:
            sent.append(update.epoch)

    # ---- whom a change concerns -----------------------------------------------------------------------------
    def _concerned(self, change: PlanChange, update: PlanUpdate) -> set[str] | None:
        """The robots ``change`` concerns (the module's rules); None: every robot."""
        if (change.levels or change.not_levelled or change.variants or change.not_varied
                or change.operator is not None or self._has_flows):
            return None
        team = self.team
        before = self.history.get(update.epoch - 1)
        if (change.links or change.links_gone) and before is None:
            return None
        chains: set[str] = set()
        for stage in (*change.placement, *change.unplaced):
            chain = team.chain_of.get(stage)
            if chain is None:
                return None
            chains.add(chain.name)
        for name in (*change.running, *change.not_running):
            if name not in self._chains_by_name:
                return None
            chains.add(name)
        out = set(change.predicted_w) | set(change.not_predicted)
        placements = [update.placement, team.placing.target] + ([before[0].placement] if before is not None else [])
        for name in chains:
            out.update(self._chain_nodes(self._chains_by_name[name], placements))
        if chains:  # the robots whose last status says they run a stage of one of them
            stages = {stage.name for name in chains for stage in self._chains_by_name[name].stages}
            out.update(robot for robot, status in team.statuses.items() if not stages.isdisjoint(status.hosted))
        if change.links or change.links_gone:
            out |= self._route_concerned(before[0].links, update.links, placements)
        return out

    @staticmethod
    def _chain_nodes(chain, placements: list[dict[str, str]]) -> set[str]:
        """A chain's source, sink and the hosts ``placements`` give its stages."""
        out = {chain.source, chain.sink}
        for stage in chain.stages:
            out.update(p[stage.name] for p in placements if stage.name in p)
        return out

    def _route_concerned(self, old_links: tuple[LinkInfo, ...], new_links: tuple[LinkInfo, ...],
                         placements: list[dict[str, str]]) -> set[str]:
        """The robots a change of the plan's links concerns: those at the ends of a link new or gone
        (their radios' media) and those whose route to a node of a chain they touch changes (routes
        as a robot finds them, `NodeRuntime._set_plan`)."""
        team = self.team
        moved = set(old_links) ^ set(new_links)
        out = {end for link in moved for end in (link.a, link.b)}
        old, new = self._runtime_network(old_links), self._runtime_network(new_links)
        reported: dict[str, set[str]] = {}  # stage -> the nodes whose last status says they run it
        for status in team.statuses.values():
            for stage in status.hosted:
                reported.setdefault(stage, set()).add(status.node)
        touched: dict[str, set[str]] = {}  # node -> the nodes of the chains it touches
        for chain in team.scenario.chains:
            nodes = self._chain_nodes(chain, placements)
            for stage in chain.stages:
                nodes |= reported.get(stage.name, set())
            for node in nodes:
                touched.setdefault(node, set()).update(nodes)
        for robot in team.robots:
            if robot not in out and any(old.path(robot, d) != new.path(robot, d)
                                        for d in sorted(touched.get(robot, ()))):
                out.add(robot)
        return out

    def _runtime_network(self, links: tuple[LinkInfo, ...]) -> Network:
        scenario = self.team.scenario
        nodes = scenario.node_names()
        known = frozenset(nodes)
        return Network(nodes, scenario.basestation,
                       [Link(a=l.a, b=l.b, medium=l.medium, group="runtime") for l in links
                        if l.a in known and l.b in known and l.medium in scenario.radios], "runtime")
