"""Publishing plans: every change of the confirmed placement goes out as a `PlanUpdate`, and is repeated.

A new plan goes out on the plan key (base stations, recorders) as its change from the plan before
(`protocol.plans`), and to each robot on its own control key, at once or later, as its change from
the plan that robot holds (`delivery.PlanDelivery`); the current plan is repeated whole to the
robots whose status says they do not run it as far as it concerns them, and on the plan key now
and then (standby base stations, recorders joining late).
"""

from __future__ import annotations

from autopower.basestation.delivery import PlanDelivery
from autopower.protocol import LinkInfo, NodeStatus, PlanChange, PlanUpdate, encode
from autopower.protocol.plans import plan_change, published_digest, sorted_plan


class PlanPublisher:
    """The coordinator's part that publishes its plans: it owns their epoch and when they go out
    (to each robot: its `delivery`)."""

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
        self.delivery = PlanDelivery(team)  # which robot gets which plan when, and what each holds
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
        """The newest plan to the robots that wait for it (`PlanDelivery.catch_up`), and the current plan
        again when it is due: on the plan key now and then, and to the robots behind it."""
        team = self.team
        if self.delivery.catch_up_due(now_wall):
            self.delivery.catch_up(team.takeover.incarnation, self.epoch)
            # their statuses say they run it within the time a new plan's do (`behind_plan` waits as long)
            self.next_republish = max(self.next_republish, now_wall + team.config.plan_republish_s)
        if now_wall >= self.next_republish:
            settled = now_wall >= self.last_republish + team.config.plan_republish_settled_s
            if settled:
                self.publish_plan(repeat=True)  # on the plan key: standby base stations, recorders joining late
            if behind := self.behind_plan():
                self.resend_plan(behind)  # to those behind only: a plan grows with the team
            elif not settled:
                self.next_republish = now_wall + team.config.plan_republish_s

    def holds_plan(self, status: NodeStatus, epoch: int | None = None) -> bool:
        """Does the node run our plan of ``epoch`` (default: the newest) as far as it concerns it
        (`PlanDelivery.holds`: the last one sent to it up to ``epoch``)?"""
        return self.delivery.holds(status, self.epoch if epoch is None else epoch)

    def behind_plan(self) -> list[str]:
        """The robots in reach whose last status does not say they run the current plan as far as it
        concerns them (`holds_plan`: late, restarted, back in reach, or their acknowledgement lost:
        statuses are best effort)."""
        team = self.team
        behind = []
        for robot in sorted(team.alive_nodes() & set(team.robots)):
            status = team.statuses.get(robot)
            if status is None or not self.holds_plan(status) or status.plan_leader != team.takeover.leader:
                behind.append(robot)
        return behind

    def deadlines(self) -> list[float]:
        """When a plan is next due to go out (the repeat: only once the mission runs)."""
        deadlines = []
        if self.plan_due:
            deadlines.append(max(self.team.wall(), self.ready_plan_unix()))
        if self.team.mission is not None:
            deadlines.append(self.next_republish)  # 0.0 until the first plan: only meaningful once started
            if self.delivery.catch_up_unix is not None:
                deadlines.append(self.delivery.catch_up_unix)
        return deadlines

    def _publishing(self) -> bool:
        """This base station runs a mission and leads the team."""
        return self.team.mission is not None and self.team.takeover.stepped_down is None

    def publish_plan(self, repeat: bool = False) -> None:
        """The current plan out: a new one (its epoch: on the plan key, and to each robot by
        `PlanDelivery.deliver`'s rules) or, ``repeat``, the current one again on the plan key."""
        if not self._publishing():
            return
        change = None
        if repeat:
            update, payload = self._published_plan()
        else:
            self.epoch += 1
            self.last_plan_unix = self.team.wall()
            update, payload, change = self._new_plan()
        self.plan_due = False
        self.team.on_own_plan(update)  # the laptop's host first: results may follow the plan at once
        self.team.bus.publish(self.team.keys.plan, payload)
        if not repeat:
            self.delivery.deliver(update, payload, change)
        self.last_republish = self.team.wall()
        self.next_republish = self.last_republish + self.team.config.plan_republish_s

    def _new_plan(self) -> tuple[PlanUpdate, bytes, PlanChange | None]:
        """(the new plan as the robots will hold it, what goes out, the change it is): its change
        from the plan before when this base station published that one (`protocol.plans`), else
        whole (None)."""
        whole = encode(self._plan_update())
        update, digest = published_digest(whole)
        base, self.change_base = self.change_base, (update, digest)
        continues = base is not None and (base[0].leader, base[0].incarnation, base[0].epoch + 1, base[0].mission) == \
            (update.leader, update.incarnation, update.epoch, update.mission)
        self.delivery.remember(update, digest, continues)
        if not continues:
            return update, whole, None
        change = plan_change(base[0], base[1], update, digest)
        return update, encode(change), change

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
        if not self._publishing():
            return
        update, payload = self._published_plan()
        self.team.on_own_plan(update)  # as a repeat to everyone does (the laptop's host skips what it has)
        self.delivery.resend(robots, update, payload)
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

