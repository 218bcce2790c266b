"""A node late for its sources takes the captures its sensors queued; only older ones are missed."""

from __future__ import annotations

import pytest

from autopower.agent.stages import SENSOR_QUEUE
from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
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
