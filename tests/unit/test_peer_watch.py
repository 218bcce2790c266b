"""`PeerWatch`: a peer is in sight while its token is and its direct statuses keep arriving."""

from __future__ import annotations

import random

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
    assert w.limits() == {"r2": 3.5}  # two periods (1 s) would be sooner than the lease and a period
    w.on_status("r2", 2.0, 0.0)
    assert w.limits() == {"r2": 5.0}  # at rest: the lease and one of its 2 s periods


def test_a_token_that_goes_while_silent_changes_nothing_and_one_that_comes_back_starts_afresh():
    w = watch()
    w.on_token("r2", True)
    w.on_status("r2", 0.5, 0.0)
    assert [n for n, _ in w.check(2.0)] == ["r2"]
    assert w.on_token("r2", False) is None  # out of sight already
    assert w.on_token("r2", True) is True
    assert w.check(10.0) == []  # not heard since it came back: no verdict yet
    assert w.on_token("r3", False) is False  # a token that goes takes its node out of sight


def test_tokens_lost_counts_the_peers_a_token_that_went_took_out_of_sight():
    w = watch()
    w.on_token("r2", True)
    w.on_status("r2", 0.5, 0.0)
    w.check(2.0)  # silent: its token going later takes nothing out of sight
    w.on_token("r2", False)
    assert w.tokens_lost == 0 and w.suspicions == 1
    w.on_token("r3", True)
    w.on_token("r3", False)
    assert w.tokens_lost == 1


def lossy_stream(w: PeerWatch, peers: tuple[str, ...], loss: float, seconds: float, seed: int = 1,
                 t0: float = 0.0) -> list[tuple[float, str]]:
    """Each peer sends a status every 0.5 s, each lost with probability ``loss``; the suspicions."""
    rng = random.Random(seed)
    suspected = []
    t = t0
    while t < t0 + seconds:
        t += 0.5
        for peer in peers:
            if rng.random() < loss:
                continue
            suspected += [(t, n) for n, _ in w.check(t - 0.001)]
            w.on_status(peer, 0.5, t + rng.uniform(0.0, 0.002))
    return suspected


def test_on_a_lossy_link_the_silence_allowed_grows_with_the_loss_seen_and_false_suspicions_stay_rare():
    peers = ("laptop", "r2", "r3")
    w = watch()
    for peer in peers:
        w.on_token(peer, True)
    # a twelfth of a robot-day at 20 % loss: 2 x 86,400 x 3 x 0.2**2 / 12 = 1,728 suspicions for a
    # detector that allows two periods; this one learns the loss in its first seconds
    suspected = lossy_stream(w, peers, 0.2, 7200.0)
    assert all(t < 60.0 for t, _ in suspected), suspected  # while it learned the loss rate
    assert len(suspected) <= 3, suspected
    assert 0.17 < w.loss("r2") < 0.23
    assert 9.0 <= w.periods_allowed("r2") <= 11.0  # 2 x 86,400 x 0.23**m <= 1/3 per peer: m = 10
    # peers that really stop (a loop stuck, its session alive) are still declared: within 12 periods
    for peer in peers:
        w.on_status(peer, 0.5, 7201.0)  # their last
    assert w.check(7201.0 + 4.5) == []  # nine periods: what this loss may take from a live peer
    assert sorted(n for n, _ in w.check(7201.0 + 6.1)) == sorted(peers)


def test_a_clean_link_keeps_two_periods_and_one_that_heals_forgets_its_loss():
    w = watch()
    w.on_token("r2", True)
    lossy_stream(w, ("r2",), 0.0, 600.0)
    assert w.loss("r2") == 0.0 and w.limits() == {"r2": 1.0}
    lossy_stream(w, ("r2",), 0.1, 600.0, t0=600.0)
    assert w.periods_allowed("r2") > 4.0
    lossy_stream(w, ("r2",), 0.0, 3600.0, t0=1200.0)  # healed: its loss decays with the statuses that arrive
    assert w.loss("r2") < 0.01 and w.periods_allowed("r2") < 4.0


def test_an_outage_is_not_a_loss_rate():
    w = watch()
    w.on_token("r2", True)
    lossy_stream(w, ("r2",), 0.0, 60.0)
    assert [n for n, _ in w.check(80.0)] == ["r2"]  # silent for 20 s: out of sight
    w.on_status("r2", 0.5, 90.0)  # back: the 60 periods it missed count as no more than its limit
    assert w.loss("r2") < 0.05
    w.on_token("r2", False)
    w.on_token("r2", True)  # its session came back: silence counts from its next status, not the last one
    w.on_status("r2", 0.5, 500.0)
    assert w.loss("r2") < 0.05


def test_the_budget_is_shared_by_the_peers_watched():
    one, many = watch(), watch()
    one.on_token("r2", True)
    for peer in ("r2",) + tuple(f"r{i}" for i in range(3, 33)):
        many.on_token(peer, True)
    for w in (one, many):
        lossy_stream(w, ("r2",), 0.1, 1800.0)
    assert many.periods_allowed("r2") > one.periods_allowed("r2")
