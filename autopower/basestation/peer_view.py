"""The base station's `PeerStatus` as one robot acts on it.

A robot reads four things of the base station's status: that it is there (the heartbeat), whom it
sees (relaying through it), the stages it runs with their generations (a newer instance of one the
robot runs stops the robot's), and the chains whose acknowledgements it wants. The last two grow
with the team (every Blob finder of a 100-robot fleet runs on the laptop: 3.2 of its 4.2 kB), and
a robot acts only on the entries of its own chains. So the base station sends each robot its own
view, addressed to it (``node/<robot>/from/<base>``), with those entries kept:

- the chains the robot touches: its sources and sinks, the stages the plan places (or targets) on
  it, the stages its last status says it runs (an instance the plan moved away is one a newer
  one must stop);
- every DAG flow (a flow names no chain of its own; they are few).

The plan epoch is the one last sent to that robot (a robot gets a new plan that changes nothing it
acts on later, `delivery.PlanDelivery`): a robot whose plan is the base station's says so.

Whom the base station sees stays whole (a robot routes through it to any other), in the shorter
of two forms: the nodes it sees, or, when it sees most of the team, the members out of its sight
(`PeerStatus.unseen`): a base station in sight of a 100-robot fleet named all 100 (494 B of each
robot's view, every status period) where the few out of sight say the same.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Mapping
from typing import TYPE_CHECKING

from autopower.model.scenario import Scenario
from autopower.protocol import Keys, NodeStatus, PeerStatus, encode

if TYPE_CHECKING:
    from autopower.basestation.coordinator import Coordinator


class PeerViews:
    """Builds each robot's view of this base station's status."""

    def __init__(self, scenario: Scenario, keys: Keys):
        self._node = scenario.basestation
        self._keys = keys
        self._chain_of_stage = {s.name: c.name for c in scenario.chains for s in c.stages}
        self._chain_names = {c.name for c in scenario.chains}
        self._team = frozenset(scenario.node_names())
        self._own: dict[str, set[str]] = {}  # robot -> chains it sources or sinks
        for chain in scenario.chains:
            for end in (chain.source, chain.sink):
                self._own.setdefault(end, set()).add(chain.name)

    def addressed(self, coordinator: Coordinator, status: NodeStatus | None, t_unix: float,
                  next_status_s: float, send_whole: Iterable[str] = ()) -> Iterator[tuple[str, str, bytes]]:
        """(robot, key, payload) for each robot the coordinator takes for alive: ``status`` as that
        robot acts on it (`view`), or, before the mission (``status`` None), that this base station
        runs no plan yet (`listening`, which has every robot send its status whole anyway).
        ``send_whole``: the robots whose whole status this base station missed (`PeerStatus.send_whole`)."""
        send_whole = set(send_whole)
        co = coordinator
        alive = co.alive_nodes()
        listening = (encode(self._short(self.listening(self._node, t_unix, alive - {self._node}, next_status_s)))
                     if status is None else None)
        whole = self._short(PeerStatus.of(status)) if status is not None else None
        placed = self._placed_chains((co.placing.placement, co.placing.target)) if status is not None else {}
        for robot in co.robots:
            if robot not in alive:
                continue
            if listening is not None:
                payload = listening
            else:
                reported = co.statuses.get(robot)
                chains = self._touched(robot, placed.get(robot, ()), reported.hosted if reported else ())
                view = self._view(whole, chains)
                sent = co.plans.delivery.sent.get(robot)
                if sent is not None and (sent[0], status.plan_epoch) == (co.takeover.incarnation, co.plans.epoch) != sent:
                    # it holds the last plan sent to it: the newest as far as it concerns it (`PlanDelivery`)
                    view = dataclasses.replace(view, plan_epoch=sent[1])
                if robot in send_whole:
                    view = dataclasses.replace(view, send_whole=True)
                payload = encode(view)
            yield robot, self._keys.addressed(robot, self._node), payload

    def chains_of(self, robot: str, placements: Iterable[Mapping[str, str]], hosted: Iterable[str]) -> set[str]:
        """The chains ``robot`` touches: its own, those of stages ``placements`` put on it and of
        the stages it reports it runs (``hosted``)."""
        return self._touched(robot, self._placed_chains(placements).get(robot, ()), hosted)

    def _placed_chains(self, placements: Iterable[Mapping[str, str]]) -> dict[str, set[str]]:
        """node -> the chains of the stages ``placements`` put on it (one pass for every robot)."""
        out: dict[str, set[str]] = {}
        for placement in placements:
            for stage, node in placement.items():
                chain = self._chain_of_stage.get(stage)
                if chain is not None:
                    out.setdefault(node, set()).add(chain)
        return out

    def _touched(self, robot: str, placed: Iterable[str], hosted: Iterable[str]) -> set[str]:
        out = set(self._own.get(robot, ()))
        out.update(placed)
        out.update(self._chain_of_stage[s] for s in hosted if s in self._chain_of_stage)
        return out

    @staticmethod
    def listening(node: str, t_unix: float, sees: Iterable[str], next_status_s: float) -> PeerStatus:
        """What a base station that runs no mission yet tells the robots: it is there and runs no
        plan (``plan_epoch`` -1), so they name their mission in their statuses, and it can take
        over the one they run (`basestation.takeover`) instead of waiting for its rival to fall
        silent. A heartbeat like any status; it hosts nothing, wants no acknowledgement."""
        return PeerStatus(node=node, t_unix=t_unix, plan_epoch=-1, battery_j=None, hosted={}, generations={},
                          links={n: True for n in sorted(sees)}, next_status_s=next_status_s)

    def view(self, status: NodeStatus, chains: set[str]) -> PeerStatus:
        """``status`` as a robot touching ``chains`` needs it."""
        return self._view(self._short(PeerStatus.of(status)), chains)

    def _short(self, whole: PeerStatus) -> PeerStatus:
        """``whole`` naming the nodes out of sight instead of those in sight when they are fewer
        (`PeerStatus.unseen`; read against the team's members, as every robot's scenario has them)."""
        seen = set(whole.links)
        unseen = self._team - seen - {whole.node}
        if len(unseen) >= len(seen) or not seen <= self._team:
            return whole
        return dataclasses.replace(whole, links={}, unseen=tuple(sorted(unseen)))

    def _view(self, whole: PeerStatus, chains: set[str]) -> PeerStatus:
        mine = {s for s in whole.hosted if self._chain_of_stage.get(s) in chains}
        return dataclasses.replace(
            whole, hosted={s: v for s, v in whole.hosted.items() if s in mine},
            generations={s: g for s, g in whole.generations.items() if s in mine},
            acks_wanted=tuple(c for c in whole.acks_wanted if c in chains or c not in self._chain_names))
