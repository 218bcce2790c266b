"""Acknowledgements addressed to producers: a consumer's `Ack` reaches the nodes that sent it frames
(the plan's producers and whoever says it holds some), no one else, and only in its own name."""

from __future__ import annotations

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.acknowledging import AckWants
from autopower.node.custody import hop_key, parse_hop_key
from autopower.protocol import Keys, NodeStatus, decode, encode
from autopower.protocol.access import TeamAccess, addressed_problem
from tests.unit.sim_team import SimTeam
from tests.unit.test_agent_migration import FC


def test_ack_wants_follow_each_peers_last_status():
    wants = AckWants()
    wants.update("r1", ("Blob-1", "Loc-1"))
    wants.update("r2", ("Blob-1",))
    assert wants.of("Blob-1") == {"r1", "r2"} and wants.of("Loc-1") == {"r1"}
    wants.update("r1", ("Loc-1",))  # r1's frames of Blob-1 were all acknowledged
    assert wants.of("Blob-1") == {"r2"} and wants.of("Loc-1") == {"r1"}
    wants.update("r2", ())
    assert wants.of("Blob-1") == set() and wants.of("nothing") == set()


def test_ack_keys_name_both_ends_and_a_robot_may_only_put_its_own():
    keys = Keys("t")
    assert keys.addressed_ends(keys.addressed("r2", "laptop")) == ("r2", "laptop")
    for other in (keys.status("r2"), keys.node_data("r2"), keys.addressed_to("r2"), f"{keys.prefix}/node/r2/ack",
                  f"{keys.prefix}/node/r2/ack/laptop/x"):
        assert keys.addressed_ends(other) is None, other
    access = TeamAccess(keys, "laptop", ("r1", "r2"))
    assert access.may_put("r1", keys.addressed("r2", "r1")) and access.may_put("laptop", keys.addressed("r1", "laptop"))
    assert not access.may_put("r1", keys.addressed("r2", "laptop"))  # not in another node's name
    assert addressed_problem(keys, keys.addressed("r2", "r1"), "laptop", 0.0, 0.0) is not None  # names another node
    assert addressed_problem(keys, keys.addressed("r2", "r1"), "r1", 100.0, 0.0) is not None  # stamped in the future
    assert addressed_problem(keys, keys.addressed("r2", "r1"), "r1", 0.0, 0.0) is None


def _team():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={"Blob-2": "laptop"}))
    team.join()
    team.run_until(3.0)
    return sc, team


def test_a_node_holding_frames_of_a_chain_the_plan_no_longer_has_it_send_gets_its_acknowledgements():
    sc, team = _team()
    laptop = team.nodes["laptop"]
    assert "r1" not in laptop.acks() or not any(parse_hop_key(k)[0] == "Blob-2" for k in laptop.acks()["r1"].consumed)
    # r1 says it holds Blob-2 frames (a stage of Blob-2 ran there and moved away, its outputs unacknowledged)
    status = decode(encode(team.nodes["r1"].status(10.0)), NodeStatus)
    laptop.on_peer_status(NodeStatus(**{**status.__dict__, "acks_wanted": ("Blob-2", *status.acks_wanted)}))
    to_r1 = laptop.acks()["r1"].consumed
    assert {hop_key("Blob-2", 0), hop_key("Blob-2", 1)} <= set(to_r1)
    # and each node's status says which acknowledgements it needs: r2 feeds Blob-2 from its camera
    assert "Blob-2" in team.nodes["r2"].status(10.0).acks_wanted


def test_an_acknowledgement_in_another_nodes_name_or_for_another_node_is_refused():
    sc, team = _team()
    r2, keys = team.nodes["r2"], team.keys
    held = len(r2.custody)
    assert held > 0  # Blob-2's frames to the laptop, not yet acknowledged (no status exchanged)
    ack = team.nodes["laptop"].acks()["r2"]
    forged = r2.errors.get("forged", 0)
    assert r2.on_message(keys.addressed("r2", "r1"), encode(ack))  # r1's key, the laptop's name
    assert r2.errors.get("forged", 0) == forged + 1 and len(r2.custody) == held
    assert not r2.on_message(keys.addressed("r3", "laptop"), encode(ack))  # addressed to r3: not r2's key
    garbled = r2.errors.get("garbled", 0)
    assert r2.on_message(keys.addressed("r2", "laptop"), b"\x94\xa2AP\x02\xa3ack\x80")
    assert r2.errors.get("garbled", 0) == garbled + 1 and len(r2.custody) == held
    assert r2.on_message(keys.addressed("r2", "laptop"), encode(ack))  # the laptop's own: taken
    assert len(r2.custody) < held
