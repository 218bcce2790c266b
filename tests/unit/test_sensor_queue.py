"""A node late for its sources takes the captures its sensors queued; only older ones are missed."""

from __future__ import annotations

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.stages import SENSOR_QUEUE
from tests.unit.sim_team import SimTeam

LAPTOP = {"Loc-1": "laptop", "Loc-2": "laptop", "Loc-3": "laptop", "Blob-2": "laptop", "Blob-3": "laptop"}


def _team():
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=10.0, pins=LAPTOP, auto_replan=False), speed=10.0)
    team.join()
    team.run_until(5.0)
    return team


@pytest.mark.parametrize("late_periods, missed", [(3, 0), (SENSOR_QUEUE - 1, 0), (20, 20 + 1 - SENSOR_QUEUE)])
def test_a_late_tick_takes_the_queued_captures_in_order_each_at_its_own_time(late_periods, missed):
    team = _team()
    r2, laptop = team.nodes["r2"], team.nodes["laptop"]
    blob = r2.sources["Blob-2"]
    seq0, due = blob.seq, blob.next_t
    period = blob.chain.period_s
    team.clock.set(due + late_periods * period)  # the loop was busy: this many more periods are due
    r2.on_timer()
    team.pump()
    taken = late_periods + 1 - missed
    assert (blob.seq - seq0, blob.missed) == (taken, missed)
    assert blob.next_t == pytest.approx(due + (late_periods + 1) * period)  # back on its grid
    # every capture reached the sink once, in order, and was charged like any other
    ledger = laptop.sinks["Blob-2"]
    assert ledger.contiguous == blob.seq and ledger.duplicates_total == 0
    assert not r2.errors and not laptop.errors
    # a capture that waited in the queue says so in its latency: the oldest waited the longest
    assert ledger.latency_ms_max >= (late_periods - missed) * period / 10.0 * 1e3 - 1e-6


def test_periods_found_missed_after_the_node_was_stopped_are_counted_apart():
    """A node whose loop comes back a second or more after its last turn was stopped (SIGSTOP by
    `fault freeze`, a suspended host): what it finds missed is `missed_stopped` too, which `up`
    does not blame on the speed-up. A loop late by a fraction of a second is merely slow."""
    from autopower.node.stages import STOPPED_AFTER_S

    team = _team()
    r2 = team.nodes["r2"]
    blob = r2.sources["Blob-2"]
    period = blob.chain.period_s
    team.clock.set(blob.next_t + 20 * period)  # 0.25 s of wall time at x10: slow, not stopped
    r2.on_timer()
    assert (blob.missed, blob.missed_stopped) == (20 + 1 - SENSOR_QUEUE, 0)
    away_s = 2.5
    assert away_s >= STOPPED_AFTER_S
    team.clock.set(team.clock.t + away_s * 10.0)
    missed_before = blob.missed
    r2.on_timer()
    found = blob.missed - missed_before
    assert found >= away_s * 10.0 / period - SENSOR_QUEUE - 1 and blob.missed_stopped == found
    stats = r2.status(1.0).sources["Blob-2"]
    assert (stats.missed, stats.missed_stopped) == (blob.missed, found)
    assert r2.resume_state()["sources"]["Blob-2"]["missed_stopped"] == found  # kept across a restart


def test_up_does_not_blame_the_speed_up_for_periods_missed_while_an_agent_was_stopped():
    from autopower.launch.summary import keep_up_warning, status_line

    def snap(missed: int, stopped: int) -> dict:
        source = {"run": 0, "produced": 1000, "missed": missed, "produced_total": 1000, "missed_stopped": stopped}
        return {"t_virtual": 100.0, "ready": True,
                "robots": {"r2": {"present": True, "status": {"sources": {"Blob-2": source}}}}}

    assert keep_up_warning(snap(100, 100), 10.0) is None  # a freeze, on any machine
    assert "missed 100 (9.1 %, 100 of them while an agent was stopped)" in status_line(snap(100, 100), 10.0)
    warning = keep_up_warning(snap(100, 40), 10.0)  # 60 of them with nothing stopped: too fast
    assert warning.startswith("60 source periods missed (5.5 %) with no agent stopped") and "--speed 10" in warning
    assert keep_up_warning(snap(5, 0), 10.0) is None  # start-up jitter


def test_up_says_which_missed_periods_a_stage_behind_its_source_caused():
    from autopower.launch.summary import keep_up_warning, run_summary

    source = {"run": 0, "produced": 1000, "missed": 80, "produced_total": 1000, "missed_stopped": 0}
    snap = {"t_virtual": 100.0, "ready": True,
            "robots": {"r2": {"present": True, "status": {"sources": {"Blob-2": source},
                                                          "counters": {"missed-periods-backlog": 30}}}}}
    warning = keep_up_warning(snap, 10.0)
    assert warning.startswith("80 source periods missed (7.4 %) with no agent stopped, 30 of them skipped because "
                              "a stage had not run the frames its source held for it"), warning
    out = run_summary(snap, team="t", speed=10, ready_after_s=1.0, wall_s=10.0)
    assert (out["periods_missed"], out["periods_missed_backlog"]) == (80, 30)
