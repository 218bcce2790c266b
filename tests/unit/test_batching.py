"""Orders in batches (issue 33 item 3): each node gets the orders of one reconcile in one put and
answers them in one, and a batch is checked whole before anything in it is carried out.

Measured on the protocol's own counts, not on timing: a 10-robot fleet's mission start (20
stages) was one put per stage each way.
"""

from __future__ import annotations

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.errors import ProtocolError
from autopower.protocol import (
    CONTROL_MESSAGES,
    INBOX_MESSAGES,
    MAX_BATCH_ITEMS,
    Assign,
    Batch,
    Prepared,
    batched,
    encode,
    unbatch,
)
from autopower.simulation.synthetic import paper_fleet
from tests.unit.sim_team import SimTeam


def _assign(stage: str = "Loc-1", generation: int = 1) -> bytes:
    return encode(Assign(stage=stage, generation=generation, chain="Loc-1", run=0, resume_seq=0))


def test_one_message_goes_as_it_is_several_as_a_batch():
    one = _assign()
    assert batched([one]) == one
    items = unbatch(batched([one, _assign("Loc-2", 2)]), CONTROL_MESSAGES)
    assert [(raw, msg.stage) for raw, msg in items] == [(one, "Loc-1"), (_assign("Loc-2", 2), "Loc-2")]
    assert [msg.stage for _, msg in unbatch(one, CONTROL_MESSAGES)] == ["Loc-1"]


@pytest.mark.parametrize("items, problem", [
    ((), "an empty batch"),
    ((_assign(), b"\x00garbage"), "batch item 2 of 2: not"),
    ((_assign(), encode(Prepared(stage="Loc-1", generation=1, node="r1"))),
     "batch item 2 of 2: message kind 'prepared' is not accepted here"),
    ((encode(Batch(items=(_assign(),))),), "batch item 1 of 1: message kind 'batch' is not accepted here"),
    ((_assign(),) * (MAX_BATCH_ITEMS + 1), f"a batch of {MAX_BATCH_ITEMS + 1} messages"),
])
def test_a_bad_batch_is_refused_whole_naming_the_item(items, problem):
    with pytest.raises(ProtocolError, match=problem.replace("(", r"\(")):
        unbatch(encode(Batch(items=items)), CONTROL_MESSAGES)


def test_a_node_takes_a_batch_with_a_bad_item_as_garbage_and_carries_out_none_of_it():
    team = SimTeam(paper_fleet(3, 3)[1], config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(2.0)
    r1 = team.nodes["r1"]
    hosted_before, garbled = dict(r1.hosted), r1.errors.get("garbled", 0)
    bad = encode(Batch(items=(_assign("Blob-2", 10**6), b"not a message")))
    assert r1.on_message(team.keys.node_control("r1"), bad)
    assert r1.errors["garbled"] == garbled + 1 and r1.hosted == hosted_before


def test_a_fleet_start_is_one_put_per_node_each_way():
    """10 robots, each a Loc and a Blob chain: the start places 20 stages. Every order of a
    reconcile to one node goes in one put and every answer to one batch in one put."""
    scenario = paper_fleet(10, 10)[1]
    pins = {f"Loc-{i}": f"r{i}" for i in (1, 2, 3)} | {"Blob-1": "r1"}  # 4 stages on 3 robots, 16 on the laptop
    team = SimTeam(scenario, config=CoordinatorConfig(speed=1.0, auto_replan=False, pins=pins))
    co = team.coordinator
    puts: list[tuple[str, int]] = []  # (node, orders in the put) on control keys
    answers: list[int] = []  # answers per put to the base station's inbox
    to_node, to_base = co.send_to, team._send

    def count_orders(node, key, payload):
        if key == team.keys.node_control(node) and not payload.startswith(b"\x94\xc4\x02AP\x02\xa4plan"):
            try:
                puts.append((node, len(unbatch(payload, CONTROL_MESSAGES))))
            except ProtocolError:
                pass  # a plan resent to this node alone
        to_node(node, key, payload)

    def count_answers(sender, dest, key, payload, bus):
        if key == team.keys.inbox:
            answers.append(len(unbatch(payload, INBOX_MESSAGES)))
        to_base(sender, dest, key, payload, bus)

    co.send_to, team._send = count_orders, count_answers
    team.join()
    team.run_until(10.0)
    stages = len(scenario.stage_names())
    assert len(co.placing.placement) == stages == 20 and not co.placing.migrations
    orders = sum(n for _, n in puts)
    assert orders == stages and co.placing.order_resends == 0
    nodes = {node for node, _ in puts}
    assert sorted(puts) == [("laptop", 16), ("r1", 2), ("r2", 1), ("r3", 1)]  # one put per node
    assert sum(answers) == stages and len(answers) == len(nodes)
