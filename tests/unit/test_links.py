"""The base station's link bookkeeping: down at once when a lease expires, debounced otherwise."""

from __future__ import annotations

from autopower.basestation.links import LinkStates, pair_name

PAIRS = {frozenset(p) for p in (("laptop", "r1"), ("laptop", "r2"), ("r1", "r2"))}
ALIVE = {"laptop", "r1", "r2"}


def states() -> LinkStates:
    return LinkStates(PAIRS, down_after_s=3.0, heal_hold_s=2.0)


def test_a_link_seen_up_then_reported_down_is_down_at_once_and_back_after_the_hold():
    links = states()
    links.seen("r1", "r2", now=0.0)
    assert links.reported("r1", {"r2": False}, ALIVE, now=10.0) == [(frozenset({"r1", "r2"}), 10.0)]
    assert links.reported("r2", {"r1": False}, ALIVE, now=10.1) == []  # already down: counted once
    links.seen("r1", "r2", now=11.0)
    assert links.healed(now=12.5) == [] and links.down  # not up long enough yet
    links.reported("r1", {"r2": False}, ALIVE, now=12.6)  # a flap: the hold starts over
    links.seen("r1", "r2", now=13.0)
    assert links.healed(now=14.9) == []
    assert links.healed(now=15.0) == [frozenset({"r1", "r2"})] and not links.down


def test_never_seen_up_or_just_rejoined_gets_the_grace():
    links = states()
    assert links.reported("r1", {"laptop": False}, ALIVE, now=0.0) == []  # start-up: maybe not connected yet
    assert links.reported("r1", {"laptop": False}, ALIVE, now=3.0) == [(frozenset({"laptop", "r1"}), 0.0)]
    links = states()
    links.seen("r1", "r2", now=0.0)
    links.rejoined("r2", now=5.0)  # back from a freeze: its sessions reconnect
    assert links.reported("r2", {"r1": False}, ALIVE, now=5.5) == []
    links.seen("r1", "r2", now=6.0)  # ... and they did
    assert not links.down


def test_reports_about_gone_nodes_or_links_outside_the_topology_are_not_failures():
    links = states()
    links.seen("r1", "r2", now=0.0)
    assert links.reported("r1", {"r2": False}, ALIVE - {"r2"}, now=1.0) == []  # r2 is gone, not the link
    assert links.reported("r1", {"r9": False, "r3": False}, ALIVE, now=1.0) == []
    assert links.lost("laptop", "r1") and not links.lost("r1", "laptop")  # the base station's own evidence
    assert pair_name(frozenset({"r1", "laptop"})) == "laptop-r1"
