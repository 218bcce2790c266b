"""A new plan goes out as its change from the one before; every node ends up holding the plan the
base station made, or waits for it whole, never a plan nobody made."""

from __future__ import annotations

import dataclasses

import pytest
from hypothesis import given, settings, strategies as st

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import ProtocolError
from autopower.model.loading import load_scenario
from autopower.protocol import LinkInfo, MissionInfo, PlanChange, PlanUpdate, Release, decode, encode
from autopower.protocol.codec import message_kind
from autopower.protocol.plans import (
    PlanAssembler,
    apply_change,
    plan_change,
    plan_digest,
    published_digest,
    sorted_plan,
)
from tests.unit.sim_team import SimTeam

MISSION = MissionInfo(scenario="fleet", accounting="paper", epoch_unix=1_700_000_000.0, speed=1, energies_j={"r1": 9e3})
LINKS = (LinkInfo(a="laptop", b="r1", medium="802.11a"), LinkInfo(a="r1", b="r2", medium="bluetooth"))


def plan(epoch: int, placement: dict[str, str], leader: str = "laptop:1", **more) -> PlanUpdate:
    fields = {"running": {"Loc-1": 0}, "links": LINKS, "predicted_w": {"r1": 1, "r2": 0.5},
              "predicted_lifetime_s": 3600, "plan_t_virtual": 2, **more}
    return sorted_plan(PlanUpdate(epoch=epoch, mission=MISSION, placement=placement, incarnation=1, leader=leader,
                                  **fields))


def published(p: PlanUpdate) -> tuple[PlanUpdate, bytes, bytes]:
    """(the plan as receivers hold it, its digest, its whole bytes), as the base station makes them."""
    whole = encode(p)
    held, digest = published_digest(whole)
    return held, digest, whole


def change_bytes(old: PlanUpdate, new: PlanUpdate) -> bytes:
    a, da, _ = published(old)
    b, db, _ = published(new)
    return encode(plan_change(a, da, b, db))


def test_a_change_makes_the_plan_the_base_station_made_and_is_a_fraction_of_it():
    old = plan(1, {f"Blob-{i}": "laptop" for i in range(100)})
    new = plan(2, {**old.placement, "Blob-7": "r1", "Blob-8": "r2"}, predicted_w={"r1": 1.25, "r2": 0.5},
               running={"Loc-1": 0, "Blob-7": 1})
    assembler = PlanAssembler()
    assembler.whole(encode(old))
    change = change_bytes(old, new)
    got = assembler.whole(change)
    assert got is not None and encode(got) == encode(published(new)[0])  # the same plan, to the byte
    assert len(change) < len(encode(new)) / 4
    body = decode(change, PlanChange)
    assert body.placement == {"Blob-7": "r1", "Blob-8": "r2"} and body.links == body.links_gone == ()
    assert body.reasons is None and body.operator is None  # as in the plan before
    assert body.predicted_w == {"r1": 1.25}  # what stayed is not sent again


def test_a_node_that_holds_another_plan_waits_for_the_whole_one():
    first, second, third = (plan(e, {"Loc-1": n}) for e, n in ((1, "laptop"), (2, "r1"), (3, "r2")))
    late = PlanAssembler()
    assert late.whole(change_bytes(first, second)) is None  # joined after the first plan
    late.whole(encode(first))
    assert late.whole(change_bytes(second, third)) is None  # missed the second
    assert late.unapplied == 2
    # a subgroup's placement published under the base station's epoch is not the base station's plan
    subgroup = PlanAssembler()
    subgroup.whole(encode(dataclasses.replace(first, placement={"Loc-1": "r2"})))
    assert subgroup.whole(change_bytes(first, second)) is None
    # whoever holds the base station's plan first keeps it when a variant of the same epoch follows
    member = PlanAssembler()
    member.whole(encode(first))
    member.whole(encode(dataclasses.replace(first, placement={"Loc-1": "r2"})))
    assert member.whole(change_bytes(first, second)).placement == {"Loc-1": "r1"}


def test_a_change_that_does_not_make_the_plan_it_names_is_refused():
    first, second = plan(1, {"Loc-1": "laptop"}), plan(2, {"Loc-1": "r1"})
    a, da, _ = published(first)
    b, db, _ = published(second)
    forged = dataclasses.replace(plan_change(a, da, b, db), placement={"Loc-1": "r2"})
    assembler = PlanAssembler()
    assembler.whole(encode(first))
    with pytest.raises(ProtocolError, match="does not make the plan it names"):
        assembler.whole(encode(forged))
    with pytest.raises(ProtocolError, match="expected a plan"):
        assembler.whole(encode(Release(stage="Loc-1", generation=3)))


def test_each_base_station_has_its_own_base_and_links_travel_only_when_they_change():
    ours, rival = plan(1, {"Loc-1": "laptop"}), plan(1, {"Loc-1": "r1"}, leader="laptop:2")
    cut = plan(2, {"Loc-1": "laptop"}, links=LINKS[:1])
    assembler = PlanAssembler()
    assembler.whole(encode(ours))
    assembler.whole(encode(rival))
    got = assembler.whole(change_bytes(ours, cut))
    body = decode(change_bytes(ours, cut), PlanChange)
    assert got.links == LINKS[:1] and body.links == () and body.links_gone == LINKS[1:]


names = st.sampled_from([f"s{i}" for i in range(12)])
maps = st.dictionaries(names, st.sampled_from(["laptop", "r1", "r2", "r3"]), max_size=12)
watts = st.dictionaries(st.sampled_from(["r1", "r2", "r3"]), st.floats(0, 10, allow_nan=False), max_size=3)


@settings(max_examples=200, deadline=None)
@given(maps, maps, watts, watts, st.sampled_from([LINKS, LINKS[:1], ()]))
def test_applying_the_change_from_any_plan_to_any_next_one_gives_that_plan(p1, p2, w1, w2, links):
    old = plan(4, p1, predicted_w=w1, levels={k: "slow" for k in p1 if k < "s5"})
    new = plan(5, p2, predicted_w=w2, links=links, variants={k: "fast" for k in p2 if k > "s5"})
    a, da, _ = published(old)
    b, db, _ = published(new)
    made = apply_change(a, decode(encode(plan_change(a, da, b, db)), PlanChange))
    assert made == b and plan_digest(made) == db


def test_a_robot_back_in_reach_is_sent_the_new_plan_whole_and_the_team_its_change():
    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(3.0)
    co = team.coordinator
    heard: dict[str, list[str | None]] = {"plan": [], "r1": [], "r2": []}
    observer = team.hub.bus("observer")
    observer.subscribe(team.keys.plan, lambda key, payload: heard["plan"].append(message_kind(payload)))
    for robot in ("r1", "r2"):
        observer.subscribe(team.keys.node_control(robot),
                           lambda key, payload, robot=robot: heard[robot].append(message_kind(payload)))
    r1_runtime = team.subscriptions.pop("r1")  # r1 hears nothing while it is away
    for handle in r1_runtime:
        handle.close()
    co.on_liveliness("r1", False)
    co.plans.publish_plan()
    team.pump()
    assert heard["plan"] and set(heard["plan"]) == {"plan-change"}  # the team follows by changes
    assert team.nodes["r2"].plan_view.order == (co.takeover.incarnation, co.plans.epoch)
    away = team.nodes["r1"].plan_view.order
    assert away < (co.takeover.incarnation, co.plans.epoch)
    team.subscriptions["r1"] = [observer.subscribe(k, lambda key, payload: team.nodes["r1"].on_message(key, payload))
                                for k in (team.keys.node_control("r1"), team.keys.plan)]
    co.on_liveliness("r1", True)
    heard["r1"].clear()
    co.plans.publish_plan()
    team.pump()
    assert "plan" in heard["r1"] and "plan" not in heard["r2"]  # whole to the one back, at once
    assert team.nodes["r1"].plan_view.order == team.nodes["r2"].plan_view.order == (co.takeover.incarnation, co.plans.epoch)
    # the same plan, whichever way it came, but for the predicted power: each robot's own alone (`robot_part`)
    r1, r2 = team.nodes["r1"].plan, team.nodes["r2"].plan
    assert dataclasses.replace(r1, predicted_w={}) == dataclasses.replace(r2, predicted_w={})
    assert set(r1.predicted_w) <= {"r1"} and set(r2.predicted_w) <= {"r2"}


def _fleet_plan(robots: list[str], epoch: int, watts: float, far_host: str) -> PlanUpdate:
    return sorted_plan(PlanUpdate(
        epoch=epoch, mission=MISSION, incarnation=1, leader="laptop:1",
        placement={**{f"Loc-{r}": r for r in robots}, "Loc-far": far_host}, running={f"Loc-{r}": 0 for r in robots},
        links=tuple(LinkInfo(a="laptop", b=r, medium="802.11a") for r in robots),
        predicted_w={r: watts for r in robots}, predicted_lifetime_s=3600.0, plan_t_virtual=float(epoch)))


def _delivered(n: int) -> tuple[dict[str, list[bytes]], list[PlanUpdate]]:
    """What each robot of an ``n``-robot team is sent of a first plan, then of the next, which moves a far
    robot's stage and predicts every robot's power anew (`PlanDelivery`, protocol 8)."""
    from types import SimpleNamespace

    from autopower.basestation.delivery import PlanDelivery

    robots = [f"r{i:04d}" for i in range(n)]
    sent: dict[str, list[bytes]] = {r: [] for r in robots}
    team = SimpleNamespace(
        scenario=SimpleNamespace(chains=[]), chain_of={}, robots=robots, alive_nodes=lambda: set(robots) | {"laptop"},
        placing=SimpleNamespace(migrations={}), statuses={}, wall=lambda: 0.0,
        config=SimpleNamespace(plan_catch_up_s=1.0), keys=SimpleNamespace(node_control=lambda r: r),
        send_to=lambda robot, key, payload: sent[robot].append(payload))
    delivery = PlanDelivery(team)
    plans = []
    for epoch, watts, far in ((1, 1.0, robots[0]), (2, 1.5, robots[1])):
        held, digest, whole = published(_fleet_plan(robots, epoch, watts, far))
        change = None if not plans else plan_change(plans[-1][0], plans[-1][1], held, digest)
        delivery.remember(held, digest, continues=bool(plans))
        delivery.deliver(held, whole if change is None else encode(change), change)
        plans.append((held, digest))
    return sent, [p for p, _ in plans]


def test_a_robot_is_sent_its_part_of_a_plan_and_a_change_of_it_that_does_not_grow_with_the_team():
    """Rule (`robot_part`): a robot's plan carries its own predicted power alone. A decision that predicts
    every robot's power anew used to send each robot the whole team's figures (327 B of a 1.1 kB change at
    100 robots); each robot's change now carries its own, and applies to the part it holds, digest and all."""
    sizes = {}
    for n in (10, 100):
        sent, plans = _delivered(n)
        robot = "r0005"
        first, second = sent[robot]
        assert message_kind(first) == "plan" and message_kind(second) == "plan-change"
        change = decode(second, PlanChange)
        assert change.predicted_w == {robot: 1.5} and change.not_predicted == ()
        assert change.placement == {"Loc-far": "r0001"}
        assembler = PlanAssembler()
        got = assembler.whole(first)
        assert got.predicted_w == {robot: 1.0}
        got = assembler.whole(second)  # digests checked: the part's, not the whole plan's
        assert got is not None and got.predicted_w == {robot: 1.5}
        assert dataclasses.replace(got, predicted_w={}) == dataclasses.replace(plans[1], predicted_w={})
        assert plan_digest(got) == change.digest
        sizes[n] = len(second)
    assert sizes[100] == sizes[10]  # the change of the far robot's stage: the same bytes at 10 and 100 robots


def test_a_plans_digest_is_that_of_its_parts_shared_hash_and_its_predicted_power():
    from autopower.protocol.plans import part_digest, robot_part, shared_digest

    p = published(plan(1, {"Loc-1": "r1"}))[0]
    assert plan_digest(p) == part_digest(shared_digest(p), p.predicted_w)
    part = robot_part(p, "r2")
    assert part.predicted_w == {"r2": 0.5} and shared_digest(part) == shared_digest(p)
    assert plan_digest(part) == part_digest(shared_digest(p), {"r2": 0.5}) != plan_digest(p)
    assert robot_part(p, "r9").predicted_w == {}
