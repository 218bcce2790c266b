"""A loop stuck in a call is named while it is stuck: where, not just that it was away."""

from __future__ import annotations

import threading
import time

from autopower.runtime.loop_watch import LoopWatch


def _stuck_in_the_file_system(entered: threading.Event, release: threading.Event) -> None:
    entered.set()
    release.wait(10)


def test_a_loop_working_past_the_limit_is_reported_once_with_the_call_it_is_in():
    entered, release = threading.Event(), threading.Event()
    loop = threading.Thread(target=_stuck_in_the_file_system, args=(entered, release))
    loop.start()
    now = [100.0]
    watch = LoopWatch("agent r9", after_s=0.5, check_s=60.0, clock=lambda: now[0], loop_thread=loop)
    try:
        assert entered.wait(5)
        assert watch.check(now[0]) is None  # waiting for an event: never a stall
        watch.working()
        now[0] += 0.4
        assert watch.check(now[0]) is None  # working, not yet for long
        now[0] += 0.2
        where = watch.check(now[0])
        assert where is not None and "_stuck_in_the_file_system" in where
        assert watch.check(now[0] + 1.0) is None and watch.stalls == 1  # one report per stall
        watch.waiting()
        watch.working()  # the next event: a new stall would be reported again
        now[0] += 0.6
        assert watch.check(now[0]) is not None and watch.stalls == 2
    finally:
        release.set()
        loop.join()
        watch.stop()


def test_a_watch_that_itself_ran_late_says_the_whole_process_was_stopped(caplog):
    # the watch's own clock jumps 2 s across one 10 ms wait: the process, not a call, was stopped
    ticks = iter([0.0, 2.01])
    stopped = threading.Event()

    def clock():
        try:
            return next(ticks)
        except StopIteration:
            stopped.set()
            return 2.01

    with caplog.at_level("WARNING", logger="autopower.runtime.loop_watch"):
        watch = LoopWatch("agent r9", after_s=0.5, check_s=0.01, idle_check_s=0.01, clock=clock)
        assert stopped.wait(5)
        watch.stop()
    assert any("did not run for 2.0 s" in r.getMessage() for r in caplog.records)


def test_a_loop_waiting_for_events_is_looked_at_seldom_and_a_stall_still_reported_soon(caplog):
    """Each look wakes the process: an idle team's agents woke ten times a second for this alone."""
    looks = []

    def clock():
        looks.append(None)
        return time.monotonic()

    with caplog.at_level("WARNING", logger="autopower.runtime.loop_watch"):
        watch = LoopWatch("agent r9", after_s=0.2, check_s=0.02, idle_check_s=0.3, clock=clock)
        try:
            time.sleep(1.0)  # the loop waits for events
            assert len(looks) <= 2 * (1.0 / 0.3 + 2), len(looks)  # two clock reads a look (every 0.02 s: 100)
            watch.working()  # a stall begins during an idle wait: reported within after_s + idle_check_s + check_s
            deadline = time.monotonic() + 0.2 + 0.3 + 0.02 + 1.0  # (and a second for a busy machine)
            while not any("busy for" in r.getMessage() for r in caplog.records):
                assert time.monotonic() < deadline, "a stall was not reported"
                time.sleep(0.01)
        finally:
            watch.stop()
