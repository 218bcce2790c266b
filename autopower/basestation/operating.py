"""Operating: the operator's commands (chains, pins, link and radio changes) and the team snapshot.

`OperatorControl` owns what the operator decided: the pins, the disabled chains (with the stages
whose failure stopped them), the links declared down and the radio changes. The other parts of the
coordinator read these and change them only through its methods (`pin`, `stage_failed`, `adopt`).
"""

from __future__ import annotations

import dataclasses
import math
import statistics
from typing import Any

from autopower.basestation.decider import AwaitDecision
from autopower.errors import AutoPowerError
from autopower.protocol import (
    AutoCommand,
    ChainCommand,
    LinkCommand,
    MigrateCommand,
    NodeStatus,
    OperatorReply,
    OperatorSettings,
    SnapshotRequest,
)
from autopower.protocol.codec import wire_data


class OperatorControl:
    """The coordinator's operator part: commands, the settings they leave, and the snapshot `status` shows."""

    def __init__(self, team, pins: dict[str, str]):
        """``team``: the `Coordinator` whose parts carry out the commands; ``pins``: stage -> node, from
        its configuration."""
        self.team = team
        for stage, node in pins.items():
            self.check_pin(stage, node)
        self.pins: dict[str, str] = dict(pins)
        self.disabled: set[str] = set()
        self.failed_stages: dict[str, str] = {}  # stage -> "node: what: why" its component was stopped
        self.radio_faults: dict[str, tuple[str | None, str | None]] = {}  # operator radio commands
        self.operator_cuts: set[frozenset[str]] = set()  # links the operator declared down

    def check_pin(self, stage: str, node: str) -> None:
        team = self.team
        if stage not in team.chain_of:
            raise AutoPowerError(f"unknown stage {stage!r}; stages: {', '.join(team.chain_of)}")
        if node not in team.scenario.node_names():
            raise AutoPowerError(f"unknown node {node!r}; nodes: {', '.join(team.scenario.node_names())}")

    def pin(self, stage: str, node: str) -> None:
        """``stage`` stays on ``node`` whatever the policy chooses (until the pins are cleared)."""
        self.pins[stage] = node

    def with_pins(self, allocation: dict[str, str], alive: set[str]) -> dict[str, str]:
        """``allocation`` with each pinned stage it places on its pinned node, where that node is alive."""
        for stage, node in self.pins.items():
            if stage in allocation and node in alive:
                allocation[stage] = node
        return allocation

    def stage_failed(self, stage: str, where: str, chain: str) -> bool:
        """A stage's component was stopped (``where``: "node: what: why"): its chain is disabled.
        True when the chain was running until now (it was not disabled already)."""
        self.failed_stages[stage] = where
        if chain in self.disabled:
            return False
        self.disabled.add(chain)
        return True

    def on_operator(self, cmd) -> OperatorReply | AwaitDecision:
        """The reply to an operator's command; `AwaitDecision` when it waits for a decision on a
        thread (the process asks `reply_when_decided` after each timer, then replies)."""
        try:
            if isinstance(cmd, SnapshotRequest):
                return OperatorReply(ok=True, message="snapshot", snapshot=self.snapshot())
            if self.team.mission is None:
                # a new base station, or one restarted while the robots run: it decides once it has heard them
                return OperatorReply(ok=False, message="no mission here yet: this base station is waiting to hear its "
                                                       "robots (it starts the mission, or takes over the running one, "
                                                       "once they speak); try again in a moment",
                                     snapshot=self.snapshot())
            if isinstance(cmd, ChainCommand):
                self.team.scenario.chain(cmd.chain)
                if cmd.enabled == (cmd.chain not in self.disabled):
                    return OperatorReply(ok=True, message=f"{cmd.chain} already {'enabled' if cmd.enabled else 'disabled'}")
                (self.disabled.discard if cmd.enabled else self.disabled.add)(cmd.chain)
                if cmd.enabled:  # a fresh start for a chain stopped by a failed component
                    for stage in self.team.scenario.chain(cmd.chain).stages:
                        self.failed_stages.pop(stage.name, None)
                self.team.deciding.event("chain-enable" if cmd.enabled else "chain-disable", chains=(cmd.chain,))
                what = "enabled" if cmd.enabled else "disabled"
                return self._replan_for_operator(f"operator {what} {cmd.chain}")
            if isinstance(cmd, MigrateCommand):
                self.check_pin(cmd.stage, cmd.to_node)
                if cmd.to_node not in self.team.alive_nodes():
                    return OperatorReply(ok=False, message=f"{cmd.to_node} is not in the team now")
                if cmd.stage not in self.team.placing.target:
                    return OperatorReply(ok=False, message=f"{cmd.stage} does not run now (chain disabled or dropped)")
                self.pin(cmd.stage, cmd.to_node)
                self.team.placing.retarget(cmd.stage, cmd.to_node)
                self.team.prediction.predict()
                self.team.placing.reconcile()
                self.team.plans.publish_plan()
                return OperatorReply(ok=True, message=f"{cmd.stage} pinned to {cmd.to_node}")
            if isinstance(cmd, AutoCommand):
                self._clear_pins()
                return self._replan_for_operator("operator cleared pins")
            if isinstance(cmd, LinkCommand):
                self._operator_link(cmd)
                return self._replan_for_operator(f"operator changed links of {cmd.node}")
        except AutoPowerError as exc:
            return OperatorReply(ok=False, message=str(exc))
        return OperatorReply(ok=False, message=f"unsupported command {type(cmd).__name__}")

    def settings(self) -> OperatorSettings:
        """What the operator decided, for the plans (a base station taking over keeps it)."""
        return OperatorSettings(pins=dict(self.pins), disabled=tuple(sorted(self.disabled)),
                                cuts=tuple(sorted(tuple(sorted(pair)) for pair in self.operator_cuts)),
                                radios=dict(self.radio_faults))

    def adopt(self, settings: OperatorSettings) -> list[str]:
        """Take over the settings a robot's plan carried; what names no stage, chain, node or radio of
        this scenario is left out (a status is network input). Returns what was adopted, in words."""
        nodes, chains = set(self.team.scenario.node_names()), {c.name for c in self.team.scenario.chains}
        self.pins = {st: n for st, n in settings.pins.items() if st in self.team.chain_of and n in nodes}
        self.disabled = {c for c in settings.disabled if c in chains}
        self.operator_cuts = {frozenset(pair) for pair in settings.cuts if set(pair) <= nodes and pair[0] != pair[1]}
        self.radio_faults = {n: media for n, media in settings.radios.items()
                             if n in nodes and all(m is None or m in self.team.scenario.radios for m in media)}
        said = [f"pins {', '.join(f'{s}->{n}' for s, n in sorted(self.pins.items()))}" if self.pins else "",
                f"disabled {', '.join(sorted(self.disabled))}" if self.disabled else "",
                f"links down {', '.join('-'.join(sorted(p)) for p in self.operator_cuts)}" if self.operator_cuts else "",
                f"radio changes of {', '.join(sorted(self.radio_faults))}" if self.radio_faults else ""]
        return [w for w in said if w]

    def _clear_pins(self) -> None:
        """Back to what the policy chose (pinned stages migrate back), then the policy is asked again."""
        self.pins.clear()
        chosen, placing = self.team.deciding.chosen, self.team.placing
        placing.set_target({s: chosen.get(s, h) for s, h in placing.target.items()})
        self.team.placing.reconcile()

    def _operator_link(self, cmd: LinkCommand) -> None:
        """An operator's link command: a link declared down (a cut link) or a radio change (a radio fault)."""
        nodes = self.team.scenario.node_names()
        for node in (cmd.node, cmd.down_peer):
            if node is not None and node not in nodes:
                raise AutoPowerError(f"link command: unknown node {node!r}; nodes: {', '.join(nodes)}")
        if cmd.down_peer is not None:
            self.operator_cuts.add(frozenset((cmd.node, cmd.down_peer)))
            self.team.deciding.event("link-cut", a=cmd.node, b=cmd.down_peer, note="operator")
            return
        for medium in (cmd.laptop_robot, cmd.robot_robot):
            if medium is not None and medium not in self.team.scenario.radios:
                raise AutoPowerError(f"link command for {cmd.node}: unknown medium {medium!r}; radios: "
                                     f"{', '.join(self.team.scenario.radios)}")
        if cmd.laptop_robot is None and cmd.robot_robot is None:
            raise AutoPowerError(f"link command for {cmd.node}: give a medium for its links to the base station "
                                 "and/or to the robots, or a peer whose link is down")
        before = self.radio_faults.get(cmd.node, (None, None))
        self.radio_faults[cmd.node] = (cmd.laptop_robot or before[0], cmd.robot_robot or before[1])
        self.team.deciding.event("radio-fault", robot=cmd.node, laptop_robot=cmd.laptop_robot,
                                 robot_robot=cmd.robot_robot,
                    note="operator")

    def _replan_for_operator(self, reason: str) -> OperatorReply | AwaitDecision:
        queued = self.team.deciding.decider.busy  # then the command goes with the question after the one out
        ok = self.team.deciding.replan(reason)
        if self.team.deciding.decider.busy:
            return AwaitDecision(ticket=self.team.deciding.asked + (1 if queued else 0))
        return self._after_replan(ok)

    def reply_when_decided(self, waiting: AwaitDecision) -> OperatorReply | None:
        """The reply to a command once its decision is carried out, or once none is coming (the
        re-plan waits for robots); None while it is still to come."""
        answered = self.team.deciding.decisions >= waiting.ticket
        if not answered and self.team.deciding.decision_pending():
            return None
        return self._after_replan(answered and self.team.deciding.plan_error is None)

    def _after_replan(self, ok: bool) -> OperatorReply:
        """The reply to a command the team's plan carries out. A re-plan that waits (robots to
        report, none in reach) is no failure: the command is noted, and the re-plan that follows
        carries it out. (It was refused as "re-plan failed: no change", though it then applied.)"""
        if not ok and self.team.deciding.replan_waiting is not None:
            return OperatorReply(ok=True, message=f"noted; {self.team.deciding.replan_waiting}")
        return OperatorReply(ok=ok, message=self._summary(ok))

    def _summary(self, ok: bool) -> str:
        if not ok:
            return f"re-plan failed: {self.team.deciding.plan_error or 'nothing feasible'}"
        planned = self.team.deciding.planned_lifetime_s()
        return (f"re-planned ({self.team.policy.name}): lifetime {planned} s; target "
                + ", ".join(f"{s}->{n}" for s, n in self.team.placing.target.items()))

    def snapshot(self) -> dict[str, Any]:
        team = self.team
        placing, deciding, prediction, takeover = team.placing, team.deciding, team.prediction, team.takeover
        network = deciding.plan_network
        robots = {}
        for name in team.robots:
            st = team.statuses.get(name)
            robots[name] = {
                "present": name in team.present, "departed": name in team.departed,
                "status": status_dict(st) if st else None,
                "predicted_w": prediction.predicted_w.get(name),
            }
        return {
            "scenario": team.scenario.name,
            "accounting": team.scenario.accounting,
            "ready": team.ready,
            "mission": dataclasses.asdict(team.mission) if team.mission else None,
            "t_virtual": team.now(),
            "epoch": team.plans.epoch,
            "incarnation": takeover.incarnation,  # plans are ordered by (incarnation, epoch)
            "leader": takeover.leader,
            # how a running team was adopted
            "takeover": dict(takeover.adopted_team) if takeover.adopted_team else None,
            "placement": dict(placing.placement),
            "target": dict(placing.target),
            "migrating": {s: {"from": m.from_node, "to": m.to_node, "phase": m.phase}
                          for s, m in placing.migrations.items()},
            "running": dict(placing.runs.running),
            "disabled": sorted(self.disabled),
            "failed_stages": dict(self.failed_stages),
            "pins": dict(self.pins),
            "media": network.media_by_group() if network else None,
            "links": [[l.a, l.b, l.medium] for l in network.links] if network else [],
            "links_down": sorted(sorted(p) for p in team.faults.links_down),
            # a plan that runs nothing (no robot left in it) lasts for ever: not a number JSON or msgpack carry
            "planned_lifetime_s": _finite(deciding.planned_lifetime_s()),
            "predicted_lifetime_s": _finite(prediction.predicted_lifetime_s),
            "reasons": dict(deciding.stage_reasons),  # stage -> why it runs there
            "policy": team.policy.name,
            "decision_reasons": list(deciding.decision_reasons),
            "schedule": [{"duration_s": p.duration_s, "allocation": dict(p.allocation),
                          "media": p.network.media_by_group()} for p in deciding.schedule],
            "revisit_at_s": deciding.revisit_at_s,
            "plan_error": deciding.plan_error,
            "robots": robots,
            "migrations_done": placing.migrations_done,
            "assignments_done": placing.assignments_done,
            "aborted": placing.aborted,
            "replans": deciding.replans,
            "decisions": {"count": deciding.decisions, "seconds": deciding.decide_s, "max_s": deciding.decide_max_s},
            "downtime_ms": _stats(placing.downtimes_ms),
            "migration_log": list(placing.migration_log),
            "first_depletion": team.first_depletion,
            "events": list(team.events),
            "faults": list(team.faults.faults),
            "adopted": placing.adopted,
        }


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _stats(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    ordered = sorted(values)
    return {"n": len(values), "mean": statistics.fmean(values), "p50": ordered[len(ordered) // 2],
            "max": ordered[-1]}


def status_dict(st: NodeStatus) -> dict[str, Any]:
    """A robot's status as the snapshot shows it. Built for every robot of every snapshot: with
    `dataclasses.asdict` a 30-robot team's snapshot took the base station's loop tens of ms."""
    try:
        return wire_data(st)
    except ValueError:  # a non-finite number (not from the wire, which refuses them): as it is
        return _plain(dataclasses.asdict(st))


def _plain(value: Any) -> Any:
    """Tuples as lists, so that a snapshot is the same after a round trip through msgpack or JSON."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value

