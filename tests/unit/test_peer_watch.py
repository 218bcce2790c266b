"""`PeerWatch`: a peer is in sight while its token is and its direct statuses keep arriving."""

from __future__ import annotations

from autopower.node.peer_watch import PeerWatch, WatchSettings


def watch() -> PeerWatch:
    return PeerWatch(WatchSettings(periods=2.0, own_period_s=0.5, lease_s=0.5))


def test_a_peer_whose_statuses_stop_goes_out_of_sight_after_two_periods_and_comes_back_with_the_next():
    w = watch()
    assert w.on_token("r2", True) is True
    assert w.check(100.0) == [] and w.next_deadline() is None  # never heard: its token is enough
    assert w.on_status("r2", 0.5, 100.0) is False  # in sight already
    assert w.next_deadline() == 101.0
    assert w.check(101.0) == []  # the limit itself is not past it
    assert [n for n, _ in w.check(101.2)] == ["r2"]
    assert "r2" in w.silent and w.suspicions == 1
    assert w.check(105.0) == []  # said once
    assert w.on_status("r2", 0.5, 105.0) is True  # back in sight
    assert "r2" not in w.silent


def test_a_resting_peer_is_judged_by_the_period_it_announced_never_sooner_than_the_lease():
    w = PeerWatch(WatchSettings(periods=2.0, own_period_s=0.5, lease_s=3.0))
    w.on_token("r2", True)
    w.on_status("r2", 0.5, 0.0)
    assert w.limits() == {"r2": 3.0}  # two periods (1 s) would be sooner than the lease
    w.on_status("r2", 2.0, 0.0)
    assert w.limits() == {"r2": 4.0}  # at rest: two of its 2 s periods


def test_a_token_that_goes_while_silent_changes_nothing_and_one_that_comes_back_starts_afresh():
    w = watch()
    w.on_token("r2", True)
    w.on_status("r2", 0.5, 0.0)
    assert [n for n, _ in w.check(2.0)] == ["r2"]
    assert w.on_token("r2", False) is None  # out of sight already
    assert w.on_token("r2", True) is True
    assert w.check(10.0) == []  # not heard since it came back: no verdict yet
    assert w.on_token("r3", False) is False  # a token that goes takes its node out of sight
