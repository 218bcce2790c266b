"""Faults: the links the team has lost and got back, and each fault from its detection to the plan that handles it.

A link counts as down after ``link_down_after_s`` of reports and as back after ``heal_hold_s`` up
(`links.LinkStates`); each change is an event for the next decision. A fault (a robot gone, a link
down) is handled once its new plan runs: placed, and every robot in reach runs its epoch.
"""

from __future__ import annotations

from collections import deque

from autopower.basestation.links import LinkStates, pair_name
from autopower.model.network import build_network
from autopower.protocol import NodeStatus


class TeamFaults:
    """The coordinator's view of what went wrong: the links' states and the faults, with the time to handle each."""

    def __init__(self, team):
        """``team``: the `Coordinator` whose deciding part hears of the changes and whose plans handle them."""
        self.team = team
        topology = build_network(team.scenario, topology=team.config.topology)
        self.links = LinkStates({frozenset((l.a, l.b)) for l in topology.links},
                                down_after_s=team.config.link_down_after_s, heal_hold_s=team.config.heal_hold_s)
        # faults as the base station saw them: detection and when the team ran its new plan
        self.faults: deque[dict] = deque(maxlen=100)

    def record(self, kind: str, target: str, detected_unix: float) -> None:
        # decide_s: the policy's wall time in the decisions made while the fault waited to be handled
        # (the base station's loop waits for it: at 20 robots, on a loaded machine, most of the time)
        self.faults.append({"kind": kind, "target": target, "detected_unix": detected_unix,
                            "decide_s": 0.0, "epoch": None, "reconfigured_unix": None})

    def decided(self, took_s: float) -> None:
        """The policy took ``took_s`` over a decision: charged to every fault still waiting to be handled."""
        for fault in self.faults:
            if fault["reconfigured_unix"] is None:
                fault["decide_s"] += took_s

    def mark_reconfigured(self) -> None:
        """A fault is handled once its new plan runs: placed, and every robot in reach runs its epoch
        as far as it concerns it (`PlanPublisher.holds_plan`).
        Not while its decision is out or due: the plan in force then is the one from before it."""
        team = self.team
        open_faults = [f for f in self.faults if f["reconfigured_unix"] is None]
        if not open_faults or not team.ready or team.deciding.decision_pending():
            return
        for fault in open_faults:
            if fault["epoch"] is None:
                fault["epoch"] = team.plans.epoch
        for fault in open_faults:
            acked = all(team.statuses.get(r) is not None
                        and team.plans.holds_plan(team.statuses[r], fault["epoch"])
                        for r in team.alive_nodes() if r in team.robot_names)
            if acked:
                fault["reconfigured_unix"] = team.wall()
                team.note(f"{fault['kind']} {fault['target']}: reconfigured "
                          f"{fault['reconfigured_unix'] - fault['detected_unix']:.3f} s after detection")

    def settled(self) -> bool:
        """No link down (its heal is timed) and no fault waiting to be reconfigured."""
        return not self.links.down and all(f["reconfigured_unix"] is not None for f in self.faults)

    @property
    def links_down(self) -> set[frozenset[str]]:
        """Links known down now (see `LinkStates`)."""
        return self.links.down

    def link_lost(self, a: str, b: str, detected_unix: float | None = None) -> None:
        """A link an end of which is this base station (seen by its own liveliness) went down."""
        team = self.team
        if self.links.lost(a, b, detected_unix or team.wall()):
            self._link_down(frozenset((a, b)), detected_unix or team.wall())
            team.deciding.replan_soon("link change")

    def link_seen(self, a: str, b: str) -> None:
        """Evidence that a link works (its ends see each other)."""
        self.links.seen(a, b, self.team.wall())

    def rejoined(self, node: str) -> None:
        """``node`` is back in sight: its links are judged afresh (`LinkStates.rejoined`)."""
        self.links.rejoined(node, self.team.wall())

    def check_links(self, status: NodeStatus) -> None:
        """A robot's view of its links: what it reports down may be a cut (`LinkStates` debounces)."""
        team = self.team
        gone = self.links.reported(status.node, status.links, team.alive_nodes(), team.wall())
        for pair, since in gone:
            self._link_down(pair, since)
        if gone:
            team.deciding.replan_soon("link change")

    def heal_links(self) -> None:
        team = self.team
        healed = self.links.healed(team.wall())
        for pair in healed:
            team.note(f"link {pair_name(pair)} is back (up for {self.links.hold_s(pair, team.wall()):g} s)")
            a, b = sorted(pair)
            team.deciding.event("link-heal", a=a, b=b)
        if healed:  # whether moving back is worth it is the policy's hysteresis
            team.deciding.replan("links back")

    def _link_down(self, pair: frozenset[str], since: float) -> None:
        team = self.team
        a, b = sorted(pair)
        self.record("link-down", pair_name(pair), since)
        now = team.wall()
        downs = self.links.flap_penalty(pair, now)
        dampened = (f" (it flaps: penalty {downs:.1f}, halving every {self.links.flap_half_life_s:g} s; back in "
                    f"plans after {self.links.hold_s(pair, now):g} s up without a break)") if downs > 1.5 else ""
        team.note(f"link {a}-{b} is down{dampened}")
        team.deciding.event("link-cut", a=a, b=b)
