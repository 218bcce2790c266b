"""The base station's link bookkeeping: down at once when a lease expires, debounced otherwise."""

from __future__ import annotations

import pytest

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
    links.reported("r1", {"r2": True}, ALIVE, now=11.0)
    assert links.healed(now=12.5) == [] and links.down  # not up long enough yet
    links.reported("r1", {"r2": False}, ALIVE, now=12.6)  # a flap: the hold starts over, and doubles
    links.reported("r1", {"r2": True}, ALIVE, now=13.0)
    assert links.healed(now=16.5) == []
    assert links.healed(now=17.0) == [frozenset({"r1", "r2"})] and not links.down


def test_a_cut_its_ends_notice_at_different_times_is_no_flap():
    # issue 31 item 3: laptop-r1 cut one way (r1 -> laptop); the base station's lease expires first,
    # and r1's statuses say the link is up until its own lease does, a moment later
    links = states()
    pair = frozenset({"laptop", "r1"})
    links.seen("laptop", "r1", now=0.0)
    assert links.lost("laptop", "r1", now=10.0)
    links.reported("r1", {"laptop": True}, ALIVE, now=10.1)  # built before r1 noticed: no evidence
    links.reported("r1", {"laptop": False}, ALIVE, now=10.3)  # r1 noticed
    assert links.flap_penalty(pair, now=10.3) == pytest.approx(1.0, abs=0.01)  # down once, not twice
    links.seen("laptop", "r1", now=20.0)  # healed: the base station sees r1 again
    links.reported("r1", {"laptop": True}, ALIVE, now=20.1)  # r1 too: now that counts
    assert links.healed(now=21.9) == []
    assert links.healed(now=22.0) == [pair]  # after heal_hold_s, as a link that failed once


def test_at_the_heal_the_later_ends_last_down_report_is_no_flap():
    links = states()
    pair = frozenset({"laptop", "r1"})
    links.seen("laptop", "r1", now=0.0)
    links.lost("laptop", "r1", now=10.0)
    links.reported("r1", {"laptop": False}, ALIVE, now=10.3)
    links.seen("laptop", "r1", now=20.0)  # healed: the base station sees r1 again ...
    links.reported("r1", {"laptop": False}, ALIVE, now=20.1)  # ... r1's status made before it did
    links.reported("r1", {"laptop": True}, ALIVE, now=20.4)
    assert links.healed(now=21.9) == [] and links.healed(now=22.0) == [pair]  # the hold of one down
    # once r1 has seen it back in a spell, its "down" is the link going down again
    links.lost("laptop", "r1", now=30.0)
    links.reported("r1", {"laptop": False}, ALIVE, now=30.3)
    links.seen("laptop", "r1", now=31.0)
    links.reported("r1", {"laptop": True}, ALIVE, now=31.1)
    links.reported("r1", {"laptop": False}, ALIVE, now=31.5)
    assert links.flap_penalty(pair, now=31.5) > 2.5  # three downs


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
    assert links.lost("laptop", "r1", now=1.0) and not links.lost("r1", "laptop", now=1.0)  # its own evidence
    assert pair_name(frozenset({"r1", "laptop"})) == "laptop-r1"


def flap(links: LinkStates, pair: frozenset, down_s: float, up_s: float, until: float, t: float = 0.0) -> list:
    """The pair seen down for ``down_s`` then up for ``up_s``, again and again; each (time, event)."""
    a, b = sorted(pair)
    events = []
    while t < until:
        if links.lost(a, b, now=t):
            events.append((t, "down"))
        t += down_s
        links.seen(a, b, now=t)
        step = 0.1
        while step <= up_s + 1e-9:
            if links.healed(now=t + step):
                events.append((round(t + step, 1), "back"))
            step += 0.1
        t += up_s
    return events


def test_a_flapping_link_is_held_out_longer_each_time_it_goes_down():
    links = states()  # heal hold 2 s
    pair = frozenset({"laptop", "r1"})
    # down 2 s, up 3 s, for a minute: without dampening, back and down again every cycle (12 each way)
    events = flap(links, pair, down_s=2.0, up_s=3.0, until=60.0)
    assert [e for _, e in events].count("down") == 2 and [e for _, e in events].count("back") == 1, events
    assert links.hold_s(pair, now=60.0) > 3.0  # its second down doubled the hold past the up spells
    # a minute of quiet halves the penalty: a link that failed once in a while is back after 2 s again
    assert links.hold_s(pair, now=600.0) == 2.0
    assert links.flap_penalty(pair, now=60.0 + 60.0) == pytest.approx(links.flap_penalty(pair, now=60.0) / 2)


def test_the_hold_is_bounded_however_much_a_link_flapped():
    links = LinkStates(PAIRS, down_after_s=3.0, heal_hold_s=2.0, max_hold_s=30.0)
    pair = frozenset({"laptop", "r1"})
    flap(links, pair, down_s=0.5, up_s=0.5, until=60.0)  # 60 downs
    assert links.hold_s(pair, now=60.0) == 30.0
    links.lost("laptop", "r1", now=60.5)
    links.seen("laptop", "r1", now=61.0)
    assert links.healed(now=90.9) == [] and links.healed(now=91.0) == [pair]
