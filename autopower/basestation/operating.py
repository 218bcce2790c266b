"""Operating: the operator's commands (chains, pins, link and radio changes) and the team snapshot.
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


class Operating:
    """The coordinator's operator part: commands and the snapshot `status` shows. Mixed into `Coordinator`, whose state it uses."""

    def on_operator(self, cmd) -> OperatorReply | AwaitDecision:
        """The reply to an operator's command; `AwaitDecision` when it waits for a decision on a
        thread (the process asks `reply_when_decided` after each timer, then replies)."""
        try:
            if isinstance(cmd, SnapshotRequest):
                return OperatorReply(ok=True, message="snapshot", snapshot=self.snapshot())
            if self.mission is None:
                # a new base station, or one restarted while the robots run: it decides once it has heard them
                return OperatorReply(ok=False, message="no mission here yet: this base station is waiting to hear its "
                                                       "robots (it starts the mission, or takes over the running one, "
                                                       "once they speak); try again in a moment",
                                     snapshot=self.snapshot())
            if isinstance(cmd, ChainCommand):
                self.scenario.chain(cmd.chain)
                if cmd.enabled == (cmd.chain not in self.disabled):
                    return OperatorReply(ok=True, message=f"{cmd.chain} already {'enabled' if cmd.enabled else 'disabled'}")
                (self.disabled.discard if cmd.enabled else self.disabled.add)(cmd.chain)
                if cmd.enabled:  # a fresh start for a chain stopped by a failed component
                    for stage in self.scenario.chain(cmd.chain).stages:
                        self.failed_stages.pop(stage.name, None)
                self._event("chain-enable" if cmd.enabled else "chain-disable", chains=(cmd.chain,))
                what = "enabled" if cmd.enabled else "disabled"
                return self._replan_for_operator(f"operator {what} {cmd.chain}")
            if isinstance(cmd, MigrateCommand):
                self._check_pin(cmd.stage, cmd.to_node)
                if cmd.to_node not in self.alive_nodes():
                    return OperatorReply(ok=False, message=f"{cmd.to_node} is not in the team now")
                if cmd.stage not in self.target:
                    return OperatorReply(ok=False, message=f"{cmd.stage} does not run now (chain disabled or dropped)")
                self.pins[cmd.stage] = cmd.to_node
                self.target[cmd.stage] = cmd.to_node
                self._predict()
                self.reconcile()
                self.publish_plan()
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

    def operator_settings(self) -> OperatorSettings:
        """What the operator decided, for the plans (a base station taking over keeps it)."""
        return OperatorSettings(pins=dict(self.pins), disabled=tuple(sorted(self.disabled)),
                                cuts=tuple(sorted(tuple(sorted(pair)) for pair in self.operator_cuts)),
                                radios=dict(self.radio_faults))

    def adopt_operator_settings(self, settings: OperatorSettings) -> list[str]:
        """Take over the settings a robot's plan carried; what names no stage, chain, node or radio of
        this scenario is left out (a status is network input). Returns what was adopted, in words."""
        nodes, chains = set(self.scenario.node_names()), {c.name for c in self.scenario.chains}
        self.pins = {st: n for st, n in settings.pins.items() if st in self.chain_of and n in nodes}
        self.disabled = {c for c in settings.disabled if c in chains}
        self.operator_cuts = {frozenset(pair) for pair in settings.cuts if set(pair) <= nodes and pair[0] != pair[1]}
        self.radio_faults = {n: media for n, media in settings.radios.items()
                             if n in nodes and all(m is None or m in self.scenario.radios for m in media)}
        said = [f"pins {', '.join(f'{s}->{n}' for s, n in sorted(self.pins.items()))}" if self.pins else "",
                f"disabled {', '.join(sorted(self.disabled))}" if self.disabled else "",
                f"links down {', '.join('-'.join(sorted(p)) for p in self.operator_cuts)}" if self.operator_cuts else "",
                f"radio changes of {', '.join(sorted(self.radio_faults))}" if self.radio_faults else ""]
        return [w for w in said if w]

    def _clear_pins(self) -> None:
        """Back to what the policy chose (pinned stages migrate back), then the policy is asked again."""
        self.pins.clear()
        self.target = {s: self.chosen.get(s, h) for s, h in self.target.items()}
        self.reconcile()

    def _operator_link(self, cmd: LinkCommand) -> None:
        """An operator's link command: a link declared down (a cut link) or a radio change (a radio fault)."""
        nodes = self.scenario.node_names()
        for node in (cmd.node, cmd.down_peer):
            if node is not None and node not in nodes:
                raise AutoPowerError(f"link command: unknown node {node!r}; nodes: {', '.join(nodes)}")
        if cmd.down_peer is not None:
            self.operator_cuts.add(frozenset((cmd.node, cmd.down_peer)))
            self._event("link-cut", a=cmd.node, b=cmd.down_peer, note="operator")
            return
        for medium in (cmd.laptop_robot, cmd.robot_robot):
            if medium is not None and medium not in self.scenario.radios:
                raise AutoPowerError(f"link command for {cmd.node}: unknown medium {medium!r}; radios: "
                                     f"{', '.join(self.scenario.radios)}")
        if cmd.laptop_robot is None and cmd.robot_robot is None:
            raise AutoPowerError(f"link command for {cmd.node}: give a medium for its links to the base station "
                                 "and/or to the robots, or a peer whose link is down")
        before = self.radio_faults.get(cmd.node, (None, None))
        self.radio_faults[cmd.node] = (cmd.laptop_robot or before[0], cmd.robot_robot or before[1])
        self._event("radio-fault", robot=cmd.node, laptop_robot=cmd.laptop_robot, robot_robot=cmd.robot_robot,
                    note="operator")

    def _replan_for_operator(self, reason: str) -> OperatorReply | AwaitDecision:
        queued = self.decider.busy  # then the command goes with the question after the one out
        ok = self.replan(reason)
        if self.decider.busy:
            return AwaitDecision(ticket=self.asked + (1 if queued else 0))
        return self._after_replan(ok)

    def reply_when_decided(self, waiting: AwaitDecision) -> OperatorReply | None:
        """The reply to a command once its decision is carried out, or once none is coming (the
        re-plan waits for robots); None while it is still to come."""
        answered = self.decisions >= waiting.ticket
        if not answered and (self.decider.busy or self.replan_due):
            return None
        return self._after_replan(answered and self.plan_error is None)

    def _after_replan(self, ok: bool) -> OperatorReply:
        """The reply to a command the team's plan carries out. A re-plan that waits (robots to
        report, none in reach) is no failure: the command is noted, and the re-plan that follows
        carries it out. (It was refused as "re-plan failed: no change", though it then applied.)"""
        if not ok and self.replan_waiting is not None:
            return OperatorReply(ok=True, message=f"noted; {self.replan_waiting}")
        return OperatorReply(ok=ok, message=self._summary(ok))

    def _summary(self, ok: bool) -> str:
        if not ok:
            return f"re-plan failed: {self.plan_error or 'nothing feasible'}"
        planned = self.planned_lifetime_s()
        return (f"re-planned ({self.policy.name}): lifetime {planned} s; target "
                + ", ".join(f"{s}->{n}" for s, n in self.target.items()))

    def snapshot(self) -> dict[str, Any]:
        robots = {}
        for name in self.robots:
            st = self.statuses.get(name)
            robots[name] = {
                "present": name in self.present, "departed": name in self.departed,
                "status": status_dict(st) if st else None,
                "predicted_w": self.predicted_w.get(name),
            }
        return {
            "scenario": self.scenario.name,
            "accounting": self.scenario.accounting,
            "ready": self.ready,
            "mission": dataclasses.asdict(self.mission) if self.mission else None,
            "t_virtual": self.now(),
            "epoch": self.epoch,
            "incarnation": self.incarnation,  # plans are ordered by (incarnation, epoch)
            "leader": self.leader,
            "takeover": dict(self.takeover) if self.takeover else None,  # how a running team was adopted
            "placement": dict(self.placement),
            "target": dict(self.target),
            "migrating": {s: {"from": m.from_node, "to": m.to_node, "phase": m.phase}
                          for s, m in self.migrations.items()},
            "running": dict(self.running),
            "disabled": sorted(self.disabled),
            "failed_stages": dict(self.failed_stages),
            "pins": dict(self.pins),
            "media": self.plan_network.media_by_group() if self.plan_network else None,
            "links": [[l.a, l.b, l.medium] for l in self.plan_network.links] if self.plan_network else [],
            "links_down": sorted(sorted(p) for p in self.links_down),
            # a plan that runs nothing (no robot left in it) lasts for ever: not a number JSON or msgpack carry
            "planned_lifetime_s": _finite(self.planned_lifetime_s()),
            "predicted_lifetime_s": _finite(self.predicted_lifetime_s),
            "reasons": dict(self.stage_reasons),  # stage -> why it runs there
            "policy": self.policy.name,
            "decision_reasons": list(self.decision_reasons),
            "schedule": [{"duration_s": p.duration_s, "allocation": dict(p.allocation),
                          "media": p.network.media_by_group()} for p in self.schedule],
            "revisit_at_s": self.revisit_at_s,
            "plan_error": self.plan_error,
            "robots": robots,
            "migrations_done": self.migrations_done,
            "assignments_done": self.assignments_done,
            "aborted": self.aborted,
            "replans": self.replans,
            "decisions": {"count": self.decisions, "seconds": self.decide_s, "max_s": self.decide_max_s},
            "downtime_ms": _stats(self.downtimes_ms),
            "migration_log": list(self.migration_log),
            "first_depletion": self.first_depletion,
            "events": list(self.events),
            "faults": list(self.faults),
            "adopted": self.adopted,
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

