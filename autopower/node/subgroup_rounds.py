"""Subgroup rounds: the robots in reach of each other reallocate among themselves while the base
station is out of their reach (the paper's future work: no global reconfiguration needed).

`SubgroupRounds` owns the state of a robot's part in them: since when the base station is out of
reach, which situation its last round handled, when it may try again after an aborted round, and
since when it knows where each stage is placed (`_lost_on`). The agreement itself (propose, vote,
commit) is `runtime.subgroup.SubgroupAgreement`, which this class builds and answers for.

No thread, socket or clock inside: the robot's process (the agent, or the simulated team's shell)
hands in the wall clock, what its relayer reaches, the peers' last statuses and what to do to
publish a status or save the resume state, and calls `tick` on every turn of its loop.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from autopower.model.scenario import Scenario
from autopower.node.runtime import NodeRuntime
from autopower.node.stages import Lifecycle
from autopower.protocol import Assign, Keys, MigrateOut, PeerStatus, Release, SubgroupMove, SubgroupPropose, encode
from autopower.runtime.bus import Bus
from autopower.runtime.signatures import Signing
from autopower.runtime.subgroup import SubgroupAgreement

log = logging.getLogger("autopower.agent.process")  # what operators grep for: the agent's log


@dataclass(frozen=True)
class RoundSettings:
    enabled: bool = True  # reallocate among the robots in reach when the base station is not
    settle_s: float = 0.3  # wall seconds the base must be out of reach before that
    timeout_s: float = 1.0  # a round not decided by then is aborted
    status_period_s: float = 0.5  # the robots' status period: fresh statuses are in after it


class SubgroupRounds:
    def __init__(self, *, runtime: NodeRuntime, scenario: Scenario, bus: Bus, keys: Keys,
                 wall: Callable[[], float], reachable: Callable[[str], bool],
                 statuses: Mapping[str, PeerStatus], settings: RoundSettings,
                 publish_status: Callable[[], object], save_resume: Callable[[], None],
                 started_unix: float, signing: Signing | None = None,
                 reached: Callable[[], set[str]] | None = None, relay: Callable[..., None] | None = None):
        self.rt = runtime
        self.node = runtime.node
        self.scenario = scenario
        self.bus = bus
        self.keys = keys
        self.wall = wall
        self.reachable = reachable
        # every node we reach at once (`Relayer.reached`): the same answers as ``reachable``, one search
        self.reached = reached
        self.statuses = statuses  # the process's: read here, never written
        self.settings = settings
        self.publish_status = publish_status
        self.save_resume = save_resume
        self.started_unix = started_unix  # when this process started (what an objection says)
        self.agreement = SubgroupAgreement(node=self.node, bus=bus, keys=keys, now=wall, on_commit=self._commit,
                                           on_abort=self._aborted, objection=self._objection,
                                           timeout_s=settings.timeout_s, signing=signing, relay=relay)
        self.base_lost_at: float | None = None
        self._done: tuple | None = None  # (members, plan order, where stages run) handled
        self._retry_at = 0.0  # after an aborted round: not before fresh statuses are in
        # stage -> (member our plan puts it on, mission time since we know it): see `_lost_on`
        self._placed_since: dict[str, tuple[str, float]] = {}
        self.committed: list[dict] = []  # the rounds this robot applied (round, members, moves, wall time)

    # ---- what the process asks -----------------------------------------------------------------
    def on_message(self, payload: bytes) -> None:
        self.agreement.on_message(payload)

    def on_member_lost(self, node: str) -> None:
        self.agreement.on_member_lost(node)

    def idle(self) -> bool:
        """No round and no settle under way: nothing here is timed."""
        return self.base_lost_at is None and self.agreement.round is None

    def wake_times(self, now: float) -> list[float]:
        """When the process's loop must wake for a round (the settle's end, a round's deadline)."""
        wake = []
        if self.base_lost_at is not None:  # the subgroup forms when the settle ends, not at the next event
            settled = max(self.base_lost_at + self.settings.settle_s, self._retry_at)
            if settled > now:  # once past, waking for it again would spin the loop (a core at 100 %)
                wake.append(settled)
        if self.rt.started and self.agreement.round is not None:  # a round times out on its own deadline
            wake.append(self.agreement.round.deadline)
        return wake

    def running_on(self, node: str) -> set[str]:
        """The stages ``node`` runs or is starting: ours as hosted here, a peer's from its last status."""
        return {stage for stage, state in self._hosted_states(node).items()
                if state in (Lifecycle.RUNNING.value, Lifecycle.STARTING.value)}

    def _hosted_states(self, node: str) -> dict[str, str]:
        """stage -> lifecycle value of what ``node`` hosts: ours as hosted here, a peer's from its last status."""
        if node == self.node:
            hosted = {s: h.lifecycle.value for s, h in self.rt.hosted.items()}
        else:
            hosted = getattr(self.statuses.get(node), "hosted", None) or {}
        return {stage: state for stage, state in hosted.items() if stage in self.rt.stage_index}

    def _runs_in(self, stage: str, state: str, members) -> bool:
        """Whether an instance in ``state`` runs ``stage`` for the subgroup ``members``.

        A starting instance waits for the state of the stage's host in our plan (a plan names a
        stage's old host until its new one reports ready): a host outside the subgroup cannot send it
        while the subgroup is cut off, and the base station that ordered the migration may have given
        it up meanwhile (it tells a host out of its reach nothing). Such an instance runs nothing, and
        the round restarts the stage as it restarts one stranded outside; counted as running, the
        round left the stage to it and the model priced work that was never done."""
        if state == Lifecycle.RUNNING.value:
            return True
        return state == Lifecycle.STARTING.value and self.rt.plan.placement.get(stage) in members

    # ---- a turn ----------------------------------------------------------------------------------
    def tick(self) -> None:
        """Base station out of reach for a while: the robots in reach reallocate among themselves."""
        rt, cfg = self.rt, self.settings
        self.agreement.on_timer()
        if not cfg.enabled or not rt.started or rt.plan is None:
            return
        base = self.scenario.basestation
        if self.reachable(base):
            self.base_lost_at = None
            self._model_out_of_reach(frozenset())
            return
        robots = [r.name for r in self.scenario.robots]
        # the robots we reach: one search over the links we know (`Relayer.reached`), not one per robot
        reached = self.reached() if self.reached is not None else {r for r in robots if self.reachable(r)}
        members = tuple(sorted({self.node} | {r for r in robots if r in reached}))
        self._model_out_of_reach(frozenset({base, *robots}) - set(members))
        now = self.wall()
        if self.base_lost_at is None:
            self.base_lost_at = now
            return
        if (now - self.base_lost_at < cfg.settle_s or members[0] != self.node
                or self.agreement.busy or now < self._retry_at):
            return
        running = self._running_placement(members)
        # The same members and plan are not the same situation: another leader's round (rounds keep
        # the epoch) may have moved a stage out of this subgroup since ours, to a robot cut off
        # since. Keyed on members and plan alone, that stage would never be restarted. Where the
        # stages run is part of what a round handled.
        key = (members, rt.plan_view.order, tuple(sorted(running.items())))
        if self._done == key:
            return
        self._done = key
        self._propose(members, running, now)

    def _propose(self, members: tuple[str, ...], running: dict[str, str], now: float) -> None:
        from autopower.policies import subgroup_reallocation

        rt, base = self.rt, self.scenario.basestation
        robots = [r.name for r in self.scenario.robots]
        network = rt.plan_view.network
        for r in robots:
            network = network.without_link(r, base) if network.medium_between(r, base) else network
        # a robot out of reach is cut off from every member (it would be a member through one that
        # reached it): a stage it runs for a member's chain is stranded there, as on the laptop
        for r in robots:
            for m in members if r not in members else ():
                network = network.without_link(r, m) if network.medium_between(r, m) else network
        energies = {}
        for r in members:
            battery = rt.meter.battery_j if r == self.node else getattr(self.statuses.get(r), "battery_j", None)
            energies[r] = max(1e-6, battery) if battery is not None else self.scenario.robot(r).energy_j
        try:
            proposal = subgroup_reallocation(self.scenario, network, members, running, energies,
                                             accounting=rt.mission.accounting)
        except Exception as exc:  # a decision that cannot be made must not stop the robot
            log.warning("agent %s: subgroup %s: no reallocation: %s", self.node, ",".join(members), exc)
            return
        for reason in proposal.reasons:
            log.info("agent %s: subgroup: %s", self.node, reason)
        if not proposal.changes_anything:
            return
        member_set = set(members)
        moves = tuple(SubgroupMove(stage=m.stage, from_node=m.from_node if m.from_node in member_set else None,
                                   to_node=m.to_node) for m in proposal.moves)
        moves += tuple(SubgroupMove(stage=s, from_node=None, to_node=proposal.allocation[s])
                       for s in proposal.started)
        # every stage the members run after the round, not only the moved ones: a member that missed
        # an earlier round learns where that round put things, and routes to them
        placement = {s: h for s, h in proposal.allocation.items() if h in member_set}
        placement.update({m.stage: m.to_node for m in moves})
        # above any generation the base station handed out; it jumps past these when it returns
        generation = int(now * 1000)
        self.agreement.propose(members, placement, moves, generation, "; ".join(proposal.reasons[:1]))

    def _model_out_of_reach(self, nodes: frozenset[str]) -> None:
        """Price the model without the nodes out of reach; a changed figure goes out at once."""
        rt = self.rt
        model_w = rt.plan_view.model_w
        rt.plan_view.set_out_of_reach(nodes)
        if rt.plan_view.model_w != model_w:
            self.publish_status()

    def _running_placement(self, members: tuple[str, ...]) -> dict[str, str]:
        """Where the stages run now, as the members see it: a round starts from this, not the plan alone.

        A robot that was not in an earlier round (out of reach then, or not yet seen) never applied
        it: its plan still names the hosts before it (the base station, say). Starting from that
        would restart, elsewhere, a stage that round already placed on a member, and it would run
        twice. So a stage whose planned host is outside the subgroup, but that a member runs (our
        own stages, the others' last statuses), starts from that member; one a member only starts
        (`_runs_in`) does not.
        """
        placement = dict(self.rt.plan.placement)
        for member in members:
            for stage, state in sorted(self._hosted_states(member).items()):
                if placement.get(stage) not in members and self._runs_in(stage, state, members):
                    placement[stage] = member
        for stage, host in list(placement.items()):
            if host in members and self._lost_on(stage, host):
                del placement[stage]  # runs nowhere: the round restarts it (`subgroup_reallocation`)
        return placement

    def _lost_on(self, stage: str, member: str) -> bool:
        """Our plan puts ``stage`` of a running chain on ``member``, whose process was restarted since
        we learnt that, and which does not host it now: it runs nowhere.

        A member killed between a round's commit and saving it comes back with the plan before the
        round, so it does not restart what the round had put on it; the others' plans still name it as
        the host, and no round would restart the stage until the base station came back. A restarted
        process says so in its statuses (`down`: the mission time its predecessor's metering stopped,
        at most a status period before it died), and what it hosts is all it has. Only a restart tells:
        a stage on its way to a member in a migration is hosted nowhere for a while (the old host
        reports it migrated, the new one has yet to take the state in). A member that died after voting
        for the round but before its commit counts too: the margin is a round's time and a status
        period.
        """
        rt = self.rt
        chain, _ = rt.stage_index.get(stage, (None, 0))
        if chain is None or chain.name not in rt.plan.running:
            return False  # a stage of a chain the operator stopped runs nowhere on purpose
        known = self._placed_since.get(stage)
        if known is None or known[0] != member:
            self._placed_since[stage] = known = (member, rt.now())
        status = self.statuses.get(member)
        if member == self.node or status is None or status.down is None or stage in (status.hosted or {}):
            return False  # (our own restart goes on with the plan we saved: the process's resume)
        margin = (self.settings.timeout_s + self.settings.status_period_s) * rt.clock.speed
        return status.down[0] >= known[1] - margin

    def _starts_here_in_vain(self, stage: str, proposal: SubgroupPropose) -> bool:
        hosted = self.rt.hosted.get(stage)
        return hosted is not None and hosted.lifecycle is Lifecycle.STARTING and not self._runs_here(stage, proposal)

    def _runs_here(self, stage: str, proposal: SubgroupPropose) -> bool:
        hosted = self.rt.hosted.get(stage)
        return hosted is not None and self._runs_in(stage, hosted.lifecycle.value, proposal.members)

    # ---- the agreement's answers -------------------------------------------------------------------
    def _objection(self, proposal: SubgroupPropose) -> str | None:
        """Why we vote no: the round would start elsewhere a stage that runs here (it would run twice)."""
        if self.rt.plan is None:
            # restarted, not yet going on with its saved plan: it can apply nothing, and a commit here
            # would fail while the round's leader took this robot for one running what the round put
            # on it; the leader tries again later
            return f"{self.node} has no plan yet (restarted {self.wall() - self.started_unix:.1f} s ago)"
        for move in proposal.moves:
            if move.to_node != self.node and move.from_node != self.node and self._runs_here(move.stage, proposal):
                return f"{move.stage} runs on {self.node}, the round starts it on {move.to_node}"
        return None

    def _aborted(self, round_id: str, why: str) -> None:
        """The leader tries again once fresh statuses are in (the same members and plan included)."""
        self._done = None
        self._retry_at = self.wall() + self.settings.status_period_s

    def _commit(self, proposal: SubgroupPropose) -> None:
        rt, me = self.rt, self.node
        for move in proposal.moves:
            chain, _ = rt.stage_index[move.stage]
            if move.from_node == me and move.to_node != me and getattr(
                    rt.hosted.get(move.stage), "lifecycle", None) is not Lifecycle.RUNNING:
                # stopped here since we reported it (a newer instance elsewhere took over, `yield_to_newer`):
                # nothing to hand over; the next round starts from where it runs
                rt.tally("subgroup-move-gone")
            elif move.from_node == me and move.to_node != me:
                rt.hosting.on_migrate_out(MigrateOut(stage=move.stage, generation=proposal.generation, to_node=move.to_node))
            elif move.from_node is None and move.to_node == me and self._runs_here(move.stage, proposal):
                rt.tally("subgroup-restart-kept")  # it runs here already: a restart would redo its inputs
            elif move.from_node is None and move.to_node == me:  # (an instance starting here in vain is replaced)
                run = rt.plan.running.get(chain.name, 0)
                rt.hosting.on_assign(Assign(stage=move.stage, generation=proposal.generation, chain=chain.name, run=run,
                                    resume_seq=None))
            elif move.to_node != me and self._starts_here_in_vain(move.stage, proposal):
                # restarted on another member: what it buffered goes there (`Hosting.on_release`)
                rt.hosting.on_release(Release(stage=move.stage, generation=proposal.generation))
        rt.plan_view.override_placement(dict(proposal.placement), {self.scenario.basestation})
        # the moved stages are placed now: a member restarted before this round started what the
        # round put on it (`_lost_on`)
        now = rt.now()
        self._placed_since.update({m.stage: (m.to_node, now) for m in proposal.moves})
        # kept at once, not with the next periodic status: killed in between, this robot came back
        # with the plan before the round and did not restart what the round had put on it
        self.save_resume()
        if proposal.leader == me:
            self._publish_prediction()
        self.publish_status()  # what runs here now, and the model's power for it, at once
        rt.tally("subgroup-commits")
        if proposal.leader == me and self.agreement.agreement_s:
            rt.counters["subgroup-agreement-us"] = int(self.agreement.agreement_s[-1] * 1e6)
        self.committed.append({"round": proposal.round_id, "members": list(proposal.members),
                               "moves": len(proposal.moves), "t_unix": self.wall()})
        log.info("agent %s: subgroup round %s committed: %s", me, proposal.round_id,
                 ", ".join(f"{m.stage} {m.from_node or '(restart)'}->{m.to_node}" for m in proposal.moves))

    def _publish_prediction(self) -> None:
        """Say what the model predicts for the agreed placement (for the recording and replay).

        Published as a `PlanUpdate` with the current epoch: agents ignore it (not newer than
        what they run), recorders log it as a decision. Each member's own status carries its
        share (`PlanView.predict_power`, at the commit).
        """
        rt = self.rt
        if not rt.plan.predicted_w:
            return
        update = dataclasses.replace(rt.plan, predicted_lifetime_s=None, plan_t_virtual=rt.now())
        self.bus.publish(self.keys.plan, encode(update))
