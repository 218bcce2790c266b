"""Taking over: a base station that starts while the team already runs learns it before deciding.

A base station that is restarted (systemd's ``Restart=on-failure``, `up`'s supervision, an
operator) finds robots that kept running without it: a mission clock, the stages they host
(possibly moved by a subgroup round while it was away), the generations of those instances,
the epoch of the plan they run, their batteries. Deciding before hearing them would start a
second mission clock and place every stage afresh while the robots keep running theirs.

So the coordinator first listens (`learn`: every robot's status, which it publishes as soon
as it sees the base station's liveliness token and then every status period). Once every robot
of the scenario has spoken, or ``CoordinatorConfig.learn_team_s`` has passed since this base
station came up (one or two status periods plus a lease: what a robot that is still running
needs to reconnect and speak), it either starts a new mission (nobody runs one) or adopts the
running one (`_adopt_team`): the team's mission clock and starting energies (not a new zero),
the running stages where they run (the newest generation wins; stale copies are released),
the chains' run numbers, the batteries; the epoch goes on from the newest one reported and the
incarnation is one above any reported (and any this host remembers), so that every agent
accepts its plans: plans are ordered by (incarnation, epoch).

Two base stations at once (one restarted while the old one was only cut off, or started twice)
learn of each other from the plans on the plan key (when they are connected) or from the robots'
statuses, which name the base station whose plan they run (`NodeStatus.plan_leader`): the one
with the older (incarnation, leader id) steps down (`on_rival_plan`, `on_rival_status`): it stops
deciding and its process exits (status 0: a service manager must not restart it), saying which
one it yielded to. The robots follow the newer one's plans from the first (plans are ordered by
incarnation first); the older one hears of it from their next status (half a second).
"""

from __future__ import annotations

import logging
import os
import secrets
import socket

from autopower.basestation.placing import Migration
from autopower.protocol import NodeStatus, PlanChange, PlanUpdate, Release
from autopower.runtime.clock import VirtualClock

log = logging.getLogger("autopower.basestation.coordinator")  # one logger for the coordinator's parts


def instance_id() -> str:
    """This base station process, as its plans name it (`PlanUpdate.leader`)."""
    return f"{socket.gethostname()}:{os.getpid()}:{secrets.token_hex(3)}"


class TakingOver:
    """The coordinator's takeover part. Mixed into `Coordinator`, whose state it uses."""

    def learn(self, status: NodeStatus) -> None:
        """A robot's status before this base station runs the mission: what the robot runs."""
        if self.mission is not None or status.node not in self.robots:
            return
        self.listening.heard_from(status)
        self.maybe_start()

    def _adopt_team(self) -> None:
        """Go on with the mission the robots run: its clock, their placement, epochs and generations."""
        reports = {n: s for n, s in self.listening.running_reports(self.alive_nodes()).items()
                   if s.mission is not None}
        newest = max(reports.values(), key=lambda s: (s.plan_incarnation, s.plan_epoch))
        mission = newest.mission
        if mission.scenario != self.scenario.name:
            self.plan_error = (f"the robots run scenario {mission.scenario!r}, this base station "
                               f"{self.scenario.name!r}: start it with the team's scenario")
            if not self._foreign_noted:
                self._foreign_noted = True
                self.note(self.plan_error)
            return
        self.mission = mission
        self.mission_unix = self.wall()
        self.clock = VirtualClock(mission.epoch_unix, mission.speed, wall_fn=self.wall)
        if mission.speed != self.config.speed:
            self.note(f"the team runs at speed {mission.speed:g}, not {self.config.speed:g}: going on at its speed")
        heard = list(self.listening.heard.values())
        self.incarnation = max(self.incarnation, max(s.plan_incarnation for s in heard) + 1)
        self.epoch = max(s.plan_epoch for s in heard)  # the next plan is one above anything running
        generations = [g for s in heard for g in s.generations.values()]
        # above every instance the robots host, and above what a subgroup hands out (wall ms)
        self.generation = max([self.generation, int(self.wall() * 1000), *generations]) + 1
        for node, status in reports.items():
            self.statuses[node] = status  # batteries, links: what the policy starts from
        # the operator's pins, disabled chains, links and radios, from the newest plan the robots run
        kept = self.operating.adopt(newest.plan_operator) if newest.plan_operator else []
        placement, stale, waiting = _placement_of(reports, set(self.chain_of))
        self.placement = placement
        for stage, (node, generation) in waiting.items():
            # its state is on its way or lost: its StageReady completes it, else the migration
            # timeout restarts it there without (`Coordinator.on_timer`), not a stage starting for good
            self.migrations[stage] = Migration(stage, generation, node, None, "transferring", self.wall())
        self.placed_generation = {stage: reports[node].generations.get(stage, 0) for stage, node in placement.items()}
        self.target = dict(placement)
        for chain in self.scenario.chains:
            runs = [s.sources[chain.name].run for s in reports.values() if chain.name in s.sources]
            if runs:
                self.runs[chain.name] = max(runs)
                self.run_live[chain.name] = True  # its sequence goes on: a new instance starts where inputs are
            elif chain.source in self.robots and chain.source not in reports:
                self.runs_unknown.add(chain.name)  # its source robot has not spoken: `_learn_runs`
            elif not chain.sourced:
                # a fan-in chain's stage names its outputs: a fresh instance in the run its sink
                # already got outputs of would give new outputs their names. Its sink says the run
                # (`_learn_runs`), and a stage that died starts the next one (`_run_for`).
                self.runs_unknown.add(chain.name)
        self._update_running()
        for node, stage in stale:
            self._send(node, Release(stage=stage, generation=self._next_generation()))
        self.next_periodic_replan = self.now() + self.config.replan_interval_s
        self.adopted += len(placement)
        self.takeover = {"up_unix": self.listening.up_unix, "adopted_unix": self.wall(), "incarnation": self.incarnation,
                         "from_robots": sorted(reports), "mission_t_s": self.now(), "stages": len(placement),
                         "previous": {"incarnation": newest.plan_incarnation, "epoch": newest.plan_epoch,
                                      "leader": newest.plan_leader}}
        self.note(f"took over a running team after {self.wall() - self.listening.up_unix:.2f} s: mission time "
                  f"{self.now():.1f} s (its clock goes on), {len(placement)} stage(s) running "
                  f"({', '.join(f'{s}@{n}' for s, n in sorted(placement.items())) or 'none'}), "
                  f"heard {', '.join(sorted(reports))}; incarnation {self.incarnation} (after {newest.plan_leader or '?'}'s "
                  f"{newest.plan_incarnation}), epochs from {self.epoch + 1}")
        if kept:
            self.note(f"kept the operator's settings: {'; '.join(kept)}")
        self.note(f"policy: {self.policy.name}")
        self.replan("took over a running team")

    def on_rival_plan(self, plan: PlanUpdate | PlanChange) -> None:
        """A plan on the plan key that another base station made (when the two are connected)."""
        if plan.leader != self.leader:
            self._rival(plan.incarnation, plan.leader, "publishes plans")

    def on_rival_status(self, status: NodeStatus) -> None:
        """A robot runs a plan we did not make: another base station reaches it (the two of us may not
        be connected: Zenoh peers do not route for each other, the robots see both)."""
        if self.mission is None or status.plan_epoch < 0 or status.plan_leader in ("", self.leader):
            return
        older = (status.plan_incarnation, status.plan_leader) < (self.incarnation, self.leader)
        if older and status.t_unix < self.mission_unix + 1.0:
            return  # made before our first plan reached it (a takeover): not a sign of anyone else
        self._rival(status.plan_incarnation, status.plan_leader, f"gives {status.node} its plans")

    def _rival(self, incarnation: int, leader: str, how: str) -> None:
        """Another base station for this team: the one with the older (incarnation, leader id) steps down."""
        if self.stepped_down is not None:
            return
        if (incarnation, leader) > (self.incarnation, self.leader):
            self.stepped_down = (f"another base station runs team {self.keys.team!r}: {leader} "
                                 f"(incarnation {incarnation}, ours {self.incarnation}) {how}; the older one "
                                 "steps down")
            self.note(f"stepping down: {self.stepped_down}")
            log.warning("base station: stepping down: %s", self.stepped_down)
        elif self._rival_seen != leader:
            self._rival_seen = leader
            self.note(f"another base station ({leader}, incarnation {incarnation}) {how} for this team; it is "
                      f"older than this one (incarnation {self.incarnation}) and steps down when it hears of us")


def _placement_of(reports: dict[str, NodeStatus], stages: set[str]
                  ) -> tuple[dict[str, str], list[tuple[str, str]], dict[str, tuple[str, int]]]:
    """(stage -> node running it, [(node, stage) copies to release], stage -> (node, generation)
    of those still waiting for their state) from the robots' statuses.

    A stage running on two nodes (an order that crossed the crash) runs where its generation is
    newest; the other copy is released. A stage that was migrating when the old base station
    died (starting on one node, already handed over by another) is taken as placed on the node
    its state went to, and as still waiting for that state: whether it arrives, nobody can tell
    from here (the handed-over copy may be a move before, and the state may have died with the
    old base station), so the adopter gives it a migration's time and then starts it without.
    """
    running: dict[str, list[tuple[int, str]]] = {}
    starting: dict[str, list[tuple[int, str]]] = {}
    handed_over: set[str] = set()
    for node, status in reports.items():
        for stage, state in status.hosted.items():
            if stage not in stages:
                continue
            gen = status.generations.get(stage, 0)
            if state == "running":
                running.setdefault(stage, []).append((gen, node))
            elif state == "starting":
                starting.setdefault(stage, []).append((gen, node))
            elif state in ("draining", "migrated"):
                handed_over.add(stage)
    placement, stale = {}, []
    for stage, hosts in running.items():
        hosts.sort(reverse=True)
        placement[stage] = hosts[0][1]
        stale += [(node, stage) for _, node in hosts[1:]]
    waiting = {}
    for stage, hosts in starting.items():
        if stage not in placement and stage in handed_over:
            generation, node = max(hosts)
            placement[stage] = node
            waiting[stage] = (node, generation)
    return placement, stale, waiting
