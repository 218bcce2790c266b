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
running one (`Takeover._adopt_team`): the team's mission clock and starting energies (not a new
zero), the running stages where they run (the newest generation wins; stale copies are released),
the chains' run numbers, the batteries; the epoch goes on from the newest one reported and the
incarnation is one above any reported (and any this host remembers), so that every agent
accepts its plans: plans are ordered by (incarnation, epoch). What it learned goes to the part
that owns it, by a call: the mission to the coordinator (`start_mission`), the epoch to the
publisher (`continue_from`), the placement, generations and runs to the placing part
(`adopt_team`), the operator's settings to the operator's part (`adopt`).

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

from autopower.basestation.listening import TeamListening
from autopower.protocol import MissionInfo, NodeStatus, PlanChange, PlanUpdate

log = logging.getLogger("autopower.basestation.coordinator")  # one logger for the coordinator's parts


def instance_id() -> str:
    """This base station process, as its plans name it (`PlanUpdate.leader`)."""
    return f"{socket.gethostname()}:{os.getpid()}:{secrets.token_hex(3)}"


class Takeover:
    """The coordinator's part that starts the mission or takes over a running one, and yields to a newer base station.

    It owns what identifies this base station's plans (``incarnation``, ``leader``), what it hears
    of the team before the mission (``listening``), how a running team was adopted
    (``adopted_team``) and why it stepped down (``stepped_down``)."""

    def __init__(self, team, *, leader: str | None, incarnation: int, up_unix: float, learn_team_s: float):
        """``team``: the `Coordinator` whose parts it starts or hands the adopted team to."""
        self.team = team
        # which start of a base station this is (plans are ordered by (incarnation, epoch)): one above
        # any the robots report when taking over; the process raises it to what its host remembers
        self.incarnation = incarnation
        self.leader = leader or instance_id()
        # what it hears of the team before it runs the mission (`basestation.listening`)
        self.listening = TeamListening(up_unix=up_unix, learn_team_s=learn_team_s)
        self.adopted_team: dict | None = None  # how the running team was adopted (None: we started the mission)
        self.stepped_down: str | None = None  # why we yielded to another base station
        self._rival_seen: str | None = None
        self._foreign_noted = False

    def learn(self, status: NodeStatus) -> None:
        """A robot's status before this base station runs the mission: what the robot runs."""
        team = self.team
        if team.mission is not None or status.node not in team.robots:
            return
        self.listening.heard_from(status)
        self.maybe_start()

    def came_into_sight(self, robot: str) -> None:
        self.listening.came_into_sight(robot, self.team.wall())

    def maybe_start(self) -> None:
        """Start the mission, or adopt the one the robots run, once the team has been heard."""
        team = self.team
        if team.mission is not None or self.stepped_down is not None:
            return
        listening, now, alive = self.listening, team.wall(), team.alive_nodes()
        if listening.takeover_due(alive, team.robots, now):
            self._adopt_team()
            return
        in_sight = team.present - team.departed
        if listening.running_reports(alive) or not listening.team_known(in_sight, now):
            return  # a running team is still to be heard, or robots in sight have not said what they run
        everyone = set(team.robots) <= team.present
        late = (listening.first_seen_unix is not None
                and now - listening.first_seen_unix >= team.config.start_grace_s)
        if not (everyone or (late and team.present)):
            return
        team.start_mission(MissionInfo(scenario=team.scenario.name, accounting=team.scenario.accounting,
                                       epoch_unix=team.wall(), speed=team.config.speed,
                                       energies_j=team.scenario.energies_j()))
        team.deciding.replan_periodically_from(team.config.replan_interval_s)
        team.note(f"policy: {team.policy.name}")
        missing = set(team.robots) - team.present
        team.note("mission started" + (f" without {', '.join(sorted(missing))}" if missing else ""))
        team.deciding.replan("mission start")

    def start_deadlines(self) -> list[float]:
        """When the mission may start without waiting any longer (none before the first robot appears)."""
        team, listening = self.team, self.listening
        if listening.first_seen_unix is None:
            return []
        return [listening.first_seen_unix + team.config.start_grace_s,  # a late start
                *listening.deadlines(team.alive_nodes(), team.robots, team.present - team.departed,
                                     team.wall())]  # done listening

    def _adopt_team(self) -> None:
        """Go on with the mission the robots run: its clock, their placement, epochs and generations."""
        team = self.team
        reports = {n: s for n, s in self.listening.running_reports(team.alive_nodes()).items()
                   if s.mission is not None}
        newest = max(reports.values(), key=lambda s: (s.plan_incarnation, s.plan_epoch))
        mission = newest.mission
        if mission.scenario != team.scenario.name:
            error = (f"the robots run scenario {mission.scenario!r}, this base station "
                     f"{team.scenario.name!r}: start it with the team's scenario")
            team.deciding.cannot_decide(error)
            if not self._foreign_noted:
                self._foreign_noted = True
                team.note(error)
            return
        team.start_mission(mission)
        if mission.speed != team.config.speed:
            team.note(f"the team runs at speed {mission.speed:g}, not {team.config.speed:g}: going on at its speed")
        heard = list(self.listening.heard.values())
        self.incarnation = max(self.incarnation, max(s.plan_incarnation for s in heard) + 1)
        team.plans.continue_from(max(s.plan_epoch for s in heard))  # the next plan is one above anything running
        generations = [g for s in heard for g in s.generations.values()]
        # above every instance the robots host, and above what a subgroup hands out (wall ms)
        team.placing.generations.above(max([int(team.wall() * 1000), *generations]))
        team.heard_statuses(reports)  # batteries, links: what the policy starts from
        # the operator's pins, disabled chains, links and radios, from the newest plan the robots run
        kept = team.operating.adopt(newest.plan_operator) if newest.plan_operator else []
        placement, stale, waiting = _placement_of(reports, set(team.chain_of))
        runs, unknown, holders = {}, set(), {}
        for chain in team.scenario.chains:
            chain_runs = [s.sources[chain.name].run for s in reports.values() if chain.name in s.sources]
            if chain_runs:
                runs[chain.name] = max(chain_runs)  # its sequence goes on: a new instance starts where inputs are
                said = reports.get(chain.source)
                if said is not None and chain.name in said.sources and said.sources[chain.name].run == runs[chain.name]:
                    # its process holds the run's position (`ChainRuns.run_for`)
                    holders[chain.name] = (team.source_sight(chain.source).sighting, said.process)
            elif chain.source in team.robots and chain.source not in reports:
                unknown.add(chain.name)  # its source robot has not spoken: `Placement.learn_runs`
            elif not chain.sourced:
                # a fan-in chain's stage names its outputs: a fresh instance in the run its sink
                # already got outputs of would give new outputs their names. Its sink says the run
                # (`Placement.learn_runs`), and a stage that died starts the next one (`ChainRuns.run_for`).
                unknown.add(chain.name)
        generation_of = {stage: reports[node].generations.get(stage, 0) for stage, node in placement.items()}
        team.placing.adopt_team(placement, generation_of, waiting, runs, unknown, stale, holders)
        team.deciding.replan_periodically_from(team.now() + team.config.replan_interval_s)
        self.adopted_team = {"up_unix": self.listening.up_unix, "adopted_unix": team.wall(),
                             "incarnation": self.incarnation, "from_robots": sorted(reports),
                             "mission_t_s": team.now(), "stages": len(placement),
                             "previous": {"incarnation": newest.plan_incarnation, "epoch": newest.plan_epoch,
                                          "leader": newest.plan_leader}}
        team.note(f"took over a running team after {team.wall() - self.listening.up_unix:.2f} s: mission time "
                  f"{team.now():.1f} s (its clock goes on), {len(placement)} stage(s) running "
                  f"({', '.join(f'{s}@{n}' for s, n in sorted(placement.items())) or 'none'}), "
                  f"heard {', '.join(sorted(reports))}; incarnation {self.incarnation} (after {newest.plan_leader or '?'}'s "
                  f"{newest.plan_incarnation}), epochs from {team.plans.epoch + 1}")
        if kept:
            team.note(f"kept the operator's settings: {'; '.join(kept)}")
        team.note(f"policy: {team.policy.name}")
        team.deciding.replan("took over a running team")

    def on_rival_plan(self, plan: PlanUpdate | PlanChange) -> None:
        """A plan on the plan key that another base station made (when the two are connected)."""
        if plan.leader != self.leader:
            self._rival(plan.incarnation, plan.leader, "publishes plans")

    def on_rival_status(self, status: NodeStatus) -> None:
        """A robot runs a plan we did not make: another base station reaches it (the two of us may not
        be connected: Zenoh peers do not route for each other, the robots see both)."""
        if self.team.mission is None or status.plan_epoch < 0 or status.plan_leader in ("", self.leader):
            return
        older = (status.plan_incarnation, status.plan_leader) < (self.incarnation, self.leader)
        if older and status.t_unix < self.team.mission_unix + 1.0:
            return  # made before our first plan reached it (a takeover): not a sign of anyone else
        self._rival(status.plan_incarnation, status.plan_leader, f"gives {status.node} its plans")

    def _rival(self, incarnation: int, leader: str, how: str) -> None:
        """Another base station for this team: the one with the older (incarnation, leader id) steps down."""
        if self.stepped_down is not None:
            return
        if (incarnation, leader) > (self.incarnation, self.leader):
            self.stepped_down = (f"another base station runs team {self.team.keys.team!r}: {leader} "
                                 f"(incarnation {incarnation}, ours {self.incarnation}) {how}; the older one "
                                 "steps down")
            self.team.note(f"stepping down: {self.stepped_down}")
            log.warning("base station: stepping down: %s", self.stepped_down)
        elif self._rival_seen != leader:
            self._rival_seen = leader
            self.team.note(f"another base station ({leader}, incarnation {incarnation}) {how} for this team; it is "
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
