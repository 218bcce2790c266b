"""Publishing plans: every change of the confirmed placement goes out as a `PlanUpdate`, and is repeated.

A new plan goes out as its change from the plan before (`protocol.plans`) to the robots that had
that one, whole to those that did not; the current plan is repeated to the robots whose status
says they do not run it, and to everyone now and then (late joiners, standby base stations).
"""

from __future__ import annotations

from autopower.protocol import LinkInfo, PlanUpdate, encode
from autopower.protocol.plans import plan_change, published_digest, sorted_plan


class PlanPublisher:
    """The coordinator's part that publishes its plans: it owns their epoch and when they go out."""

    def __init__(self, team):
        """``team``: the `Coordinator` whose mission, placement, decision and settings a plan carries."""
        self.team = team
        self.epoch = 0
        self.next_republish = 0.0
        self.last_republish = 0.0  # when the plan last went out (new or repeated)
        self.last_plan_unix = 0.0  # when the last new plan went out (`CoordinatorConfig.plan_batch_s`)
        # the last new plan as the robots decode it, and its digest: the next new plan goes out as
        # its change from this one (`protocol.plans`)
        self.change_base: tuple[PlanUpdate, bytes] | None = None
        self.plan_reached: set[str] = set()  # the robots in reach when the last new plan went out
        # a stage became ready: the plan goes out once, at the next timer, for every stage that
        # became ready meanwhile (a fleet's start makes a plan per stage otherwise: O(stages^2))
        self.plan_due = False

    def continue_from(self, epoch: int) -> None:
        """The next plan is the one after ``epoch`` (a team taken over runs plans up to it)."""
        self.epoch = epoch

    def mark_due(self) -> None:
        """A stage became ready: the plan goes out at the next timer (`publish_ready`)."""
        self.plan_due = True

    def ready_plan_unix(self) -> float:
        """When a plan announcing ready stages may go: at once when no order waits for its answer
        (the wave is complete), else `plan_batch_s` after the last new plan (more answers are coming)."""
        return 0.0 if not self.team.placing.migrations else self.last_plan_unix + self.team.config.plan_batch_s

    def publish_ready(self, now_wall: float) -> None:
        """The plan announcing the stages that became ready, once it is due."""
        if self.plan_due and now_wall >= self.ready_plan_unix():
            self.publish_plan()

    def republish(self, now_wall: float) -> None:
        """The current plan again, when it is due: to everyone now and then, else to the robots behind it."""
        team = self.team
        if now_wall >= self.next_republish:
            if now_wall >= self.last_republish + team.config.plan_republish_settled_s:
                self.publish_plan(repeat=True)  # to everyone: standby base stations, late joiners unknown here
            elif behind := self.behind_plan():
                self.resend_plan(behind)  # to those behind only: a plan grows with the team
            else:
                self.next_republish = now_wall + team.config.plan_republish_s

    def behind_plan(self) -> list[str]:
        """The robots in reach whose last status does not say they run the current plan (late,
        restarted, back in reach, or their acknowledgement lost: statuses are best effort)."""
        team = self.team
        behind = []
        for robot in sorted(team.alive_nodes() & set(team.robots)):
            status = team.statuses.get(robot)
            if status is None or not team.runs_plan(status, self.epoch) or status.plan_leader != team.takeover.leader:
                behind.append(robot)
        return behind

    def deadlines(self) -> list[float]:
        """When a plan is next due to go out (the repeat: only once the mission runs)."""
        deadlines = []
        if self.plan_due:
            deadlines.append(max(self.team.wall(), self.ready_plan_unix()))
        if self.team.mission is not None:
            deadlines.append(self.next_republish)  # 0.0 until the first plan: only meaningful once started
        return deadlines

    def publish_plan(self, repeat: bool = False) -> None:
        if self.team.mission is None or self.team.takeover.stepped_down is not None:
            return
        changed_only = False
        if repeat:
            update, payload = self._published_plan()
        else:
            self.epoch += 1
            self.last_plan_unix = self.team.wall()
            update, payload, changed_only = self._new_plan()
        self.plan_due = False
        self.team.on_own_plan(update)  # the laptop's host first: results may follow the plan at once
        alive = self.team.alive_nodes()  # (a set built per call: once, not once per robot)
        in_reach = [r for r in self.team.robots if r in alive]
        self.team.bus.publish(self.team.keys.plan, payload)
        self.team.also_relay(in_reach, self.team.keys.plan, payload)
        if not repeat:
            # a robot out of reach when the plan before went out (back from a cut, restarted, late)
            # cannot apply a change from it: it is sent this plan whole at once, not a second later
            # as one behind (its status names the plan it runs only after this one went out)
            back = [r for r in in_reach if r not in self.plan_reached]
            if back and changed_only:
                self.resend_plan(back)
            self.plan_reached = set(in_reach)
        self.last_republish = self.team.wall()
        self.next_republish = self.last_republish + self.team.config.plan_republish_s

    def _new_plan(self) -> tuple[PlanUpdate, bytes, bool]:
        """(the new plan as the robots will hold it, what goes out, whether that is a change):
        its change from the plan before when this base station published that one
        (`protocol.plans`), else whole."""
        whole = encode(self._plan_update())
        update, digest = published_digest(whole)
        base, self.change_base = self.change_base, (update, digest)
        if base is None or (base[0].leader, base[0].incarnation, base[0].epoch + 1, base[0].mission) != \
                (update.leader, update.incarnation, update.epoch, update.mission):
            return update, whole, False
        return update, encode(plan_change(base[0], base[1], update, digest)), True

    def _published_plan(self) -> tuple[PlanUpdate, bytes]:
        """(the current plan, whole): the one published for this epoch, so that a robot given it
        applies the next change (a plan made again may differ in what changed since)."""
        if self.change_base is not None and (self.change_base[0].incarnation, self.change_base[0].epoch) == \
                (self.team.takeover.incarnation, self.epoch):
            update = self.change_base[0]
        else:
            update = self._plan_update()
        return update, encode(update)

    def resend_plan(self, robots: list[str]) -> None:
        """The current plan again, to ``robots`` only, on their control keys (relayed if out of sight)."""
        if self.team.mission is None or self.team.takeover.stepped_down is not None:
            return
        update, payload = self._published_plan()
        self.team.on_own_plan(update)  # as a repeat to everyone does (the laptop's host skips what it has)
        for robot in robots:
            self.team.send_to(robot, self.team.keys.node_control(robot), payload)
        self.next_republish = self.team.wall() + self.team.config.plan_republish_s

    def _plan_update(self) -> PlanUpdate:
        team = self.team
        deciding, prediction, takeover = team.deciding, team.prediction, team.takeover
        network = deciding.plan_network
        links = tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in network.links) if network else ()
        update = PlanUpdate(epoch=self.epoch, mission=team.mission, placement=dict(team.placing.placement),
                            running=dict(team.placing.runs.running), links=links, predicted_w=prediction.placement_w(),
                            predicted_lifetime_s=prediction.predicted_lifetime_s, plan_t_virtual=prediction.plan_t_virtual,
                            policy=team.policy.name, reasons=tuple(deciding.decision_reasons), levels=dict(prediction.levels),
                            variants=dict(team.variants), incarnation=takeover.incarnation, leader=takeover.leader,
                            operator=team.operating.settings())
        return sorted_plan(update)  # one order on every node, whole plan or change (`protocol.plans`)

