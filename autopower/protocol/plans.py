"""Plans on the wire: whole (`PlanUpdate`) or as their change from the plan before (`PlanChange`).

The base station publishes each new plan to every robot. Whole, a plan grows with the team
(placement, links, predicted power: 14.5 kB at 100 robots) and a new plan mostly moves a few
stages, so a new epoch goes out as its change; repeats and resends to a robot behind stay whole.

Rules that keep every node on the same plan:
- a change applies only to the plan it was made from: same leader, incarnation and epoch, and
  the same bytes (``base_digest``). A node that holds another plan for that epoch (a subgroup's
  placement published for the recording, a repeat made after the operator changed a setting)
  waits for the whole plan, as a node that missed a plan always did;
- the result is checked against ``digest`` before it is used: a change applied wrongly is
  refused, never run;
- of two whole plans with the same (incarnation, epoch) from one leader, the first one seen is
  kept as the base: the base station's own comes first, and a later one is someone's variant;
- a plan's maps and links are sorted (`sorted_plan`): a node iterates a plan the same way
  whichever form it got, and a change names only the links new and gone (routes do not depend
  on the links' order: the tie-break is the nodes' order, `model.network`).
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping
from typing import TypeVar

import msgpack

from autopower.errors import ProtocolError
from autopower.protocol.codec import decode, encode, message_kind
from autopower.protocol.messages import LinkInfo, PlanChange, PlanUpdate

DIGEST_BYTES = 16
KEPT_LEADERS = 4  # base stations whose last plan a node keeps (two at once during a takeover)

V = TypeVar("V")


def plan_digest(plan: PlanUpdate) -> bytes:
    """What identifies a plan's content: a hash of its encoding. Hash a plan as a receiver holds
    it, decoded (an int where the message says float is written back as a float): the base
    station hashes ``decode(encode(plan))``, `published_digest`.

    In two parts (protocol 8): the plan without its predicted power (`shared_digest`), then its
    predicted power (`part_digest`). Each robot is sent the plan with its own predicted power
    alone (`robot_part`): the base station hashes the part every robot shares once per plan, and
    each robot's part in time independent of the team."""
    plan = sorted_plan(plan)
    return part_digest(shared_digest(plan), plan.predicted_w)


def shared_digest(plan: PlanUpdate) -> bytes:
    """The hash of a sorted plan (`sorted_plan`) without its predicted power: what every robot's part
    of it shares (`plan_digest`)."""
    return hashlib.blake2b(encode(dataclasses.replace(plan, predicted_w={})), digest_size=DIGEST_BYTES).digest()


def part_digest(shared: bytes, predicted_w: Mapping[str, float]) -> bytes:
    """`plan_digest` of a plan whose `shared_digest` is ``shared`` and whose predicted power is ``predicted_w``."""
    power = msgpack.packb(sorted(predicted_w.items()), use_bin_type=True)
    return hashlib.blake2b(shared + power, digest_size=DIGEST_BYTES).digest()


def robot_part(plan: PlanUpdate, robot: str) -> PlanUpdate:
    """``plan`` as ``robot`` is sent it: its own predicted power alone (the only one it acts on: its
    status's ``model_w``, its recording's prediction), the rest whole. A robot's subgroup rounds
    place the whole team's stages over the whole network when the base station is gone (every
    robot may be the round's leader), so the placement, runs and links stay whole."""
    own = plan.predicted_w.get(robot)
    return dataclasses.replace(plan, predicted_w={} if own is None else {robot: own})


def published_digest(payload: bytes) -> tuple[PlanUpdate, bytes]:
    """(the plan as every receiver decodes it, its digest) of a whole plan's bytes."""
    plan = decode(payload, PlanUpdate)
    return plan, plan_digest(plan)


def _changed(old: Mapping[str, V], new: Mapping[str, V]) -> tuple[dict[str, V], tuple[str, ...]]:
    """(entries new or changed, keys gone) from ``old`` to ``new``."""
    return ({k: v for k, v in new.items() if k not in old or old[k] != v},
            tuple(sorted(k for k in old if k not in new)))


def _applied(old: Mapping[str, V], changed: Mapping[str, V], gone: tuple[str, ...]) -> dict[str, V]:
    """``old`` with ``changed`` set and ``gone`` removed, keys sorted (plans carry sorted maps,
    `sorted_plan`, so a plan built here encodes to the bytes the base station hashed)."""
    out = {k: v for k, v in old.items() if k not in gone}
    out.update(changed)
    return dict(sorted(out.items()))


def sorted_plan(plan: PlanUpdate) -> PlanUpdate:
    """``plan`` with its maps in key order: one content, one encoding. The base station publishes
    its plans so, and `apply_change` builds them so: every node iterates a plan's maps in the same
    order, whether it was sent the whole plan or its change."""
    return dataclasses.replace(plan, links=tuple(sorted(plan.links, key=_link_order)),
                               placement=dict(sorted(plan.placement.items())),
                               running=dict(sorted(plan.running.items())),
                               predicted_w=dict(sorted(plan.predicted_w.items())),
                               levels=dict(sorted(plan.levels.items())),
                               variants=dict(sorted(plan.variants.items())))


def _link_order(link: LinkInfo) -> tuple[str, str, str]:
    return link.a, link.b, link.medium


def _same_or_none(old: V, new: V) -> V | None:
    return None if new == old else new


def plan_change(base: PlanUpdate, base_digest: bytes, new: PlanUpdate, new_digest: bytes) -> PlanChange:
    """``new`` as its change from ``base`` (the plan before it from the same base station)."""
    if (base.leader, base.incarnation, base.mission) != (new.leader, new.incarnation, new.mission):
        raise ValueError("a plan change follows a plan of the same base station and mission")
    placement, unplaced = _changed(base.placement, new.placement)
    running, not_running = _changed(base.running, new.running)
    predicted_w, not_predicted = _changed(base.predicted_w, new.predicted_w)
    levels, not_levelled = _changed(base.levels, new.levels)
    variants, not_varied = _changed(base.variants, new.variants)
    return PlanChange(epoch=new.epoch, incarnation=new.incarnation, leader=new.leader, base_epoch=base.epoch,
                      base_digest=base_digest, digest=new_digest,
                      placement=placement, unplaced=unplaced, running=running, not_running=not_running,
                      links=tuple(sorted(set(new.links) - set(base.links), key=_link_order)),
                      links_gone=tuple(sorted(set(base.links) - set(new.links), key=_link_order)),
                      predicted_w=predicted_w, not_predicted=not_predicted, levels=levels, not_levelled=not_levelled,
                      variants=variants, not_varied=not_varied, predicted_lifetime_s=new.predicted_lifetime_s,
                      plan_t_virtual=new.plan_t_virtual, policy=_same_or_none(base.policy, new.policy),
                      reasons=_same_or_none(base.reasons, new.reasons),
                      operator=_same_or_none(base.operator, new.operator))


def apply_change(base: PlanUpdate, change: PlanChange) -> PlanUpdate:
    """The plan ``change`` makes of ``base`` (not checked: `PlanAssembler` checks the digests)."""
    return PlanUpdate(epoch=change.epoch, mission=base.mission,
                      placement=_applied(base.placement, change.placement, change.unplaced),
                      running=_applied(base.running, change.running, change.not_running),
                      links=tuple(sorted((set(base.links) - set(change.links_gone)) | set(change.links),
                                         key=_link_order)),
                      predicted_w=_applied(base.predicted_w, change.predicted_w, change.not_predicted),
                      predicted_lifetime_s=change.predicted_lifetime_s, plan_t_virtual=change.plan_t_virtual,
                      policy=base.policy if change.policy is None else change.policy,
                      reasons=base.reasons if change.reasons is None else change.reasons,
                      levels=_applied(base.levels, change.levels, change.not_levelled),
                      variants=_applied(base.variants, change.variants, change.not_varied),
                      incarnation=change.incarnation, leader=change.leader,
                      operator=base.operator if change.operator is None else change.operator)


class PlanAssembler:
    """Turns what arrives on the plan keys into whole plans, keeping each base station's last one
    as the base for its next change."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[PlanUpdate, bytes | None]] = {}  # leader -> (plan, digest once known)
        self.unapplied = 0  # changes that did not follow the plan held (a whole one is needed)

    def whole(self, payload: bytes) -> PlanUpdate | None:
        """The whole plan ``payload`` carries or makes; None for a change this node cannot apply.
        Raises `ProtocolError` for anything but a plan or a plan change."""
        kind = message_kind(payload)
        if kind == PlanUpdate.KIND:
            plan = decode(payload, PlanUpdate)
            self.remember(plan)
            return plan
        if kind != PlanChange.KIND:
            raise ProtocolError(f"expected a plan or a plan change, got {kind!r}")
        change = decode(payload, PlanChange)
        held = self._last.get(change.leader)
        if held is None or (held[0].incarnation, held[0].epoch) != (change.incarnation, change.base_epoch):
            self.unapplied += 1
            return None
        base, digest = held
        if digest is None:
            digest = plan_digest(base)
            self._last[change.leader] = (base, digest)  # the next change of the same base finds it
        if digest != change.base_digest:
            self.unapplied += 1
            return None
        plan = apply_change(base, change)
        if plan_digest(plan) != change.digest:
            raise ProtocolError(f"plan change to epoch {change.epoch} does not make the plan it names")
        self._hold(plan, change.digest)
        return plan

    def remember(self, plan: PlanUpdate) -> None:
        """``plan`` is the base for the next change of its leader if it is newer than the one held
        (a node's own base station hands its host the plan before publishing it)."""
        held = self._last.get(plan.leader)
        if held is None or (plan.incarnation, plan.epoch) > (held[0].incarnation, held[0].epoch):
            self._hold(plan, None)

    def _hold(self, plan: PlanUpdate, digest: bytes | None) -> None:
        self._last.pop(plan.leader, None)
        self._last[plan.leader] = (plan, digest)
        while len(self._last) > KEPT_LEADERS:  # the base station heard from longest ago goes
            del self._last[next(iter(self._last))]
