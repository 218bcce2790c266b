"""The launcher's restart policy: backoff, start limit, bad configuration given up at once."""

from __future__ import annotations

from autopower.launch.supervisor import RestartPolicy, Supervisor


def test_backoff_doubles_up_to_its_cap():
    policy = RestartPolicy(initial_backoff_s=0.2, max_backoff_s=1.0)
    assert [policy.backoff_s(n) for n in range(1, 6)] == [0.2, 0.4, 0.8, 1.0, 1.0]


def test_a_crash_is_restarted_after_its_backoff_and_reported():
    sup = Supervisor(RestartPolicy(initial_backoff_s=0.5))
    event = sup.crashed("r2", -9, now=100.0)
    assert event.kind == "crashed" and "SIGKILL" in event.detail and "0.5 s" in event.detail
    assert sup.waiting("r2") and sup.due(now=100.4) == [] and sup.due(now=100.5) == ["r2"]
    assert sup.restarted("r2").kind == "restarted"
    assert not sup.waiting("r2") and sup.due(now=200.0) == []
    report = sup.report()
    assert report["restarts"] == {"r2": 1} and report["crashes"] == 1 and report["given_up"] == {}
    assert [e["kind"] for e in report["events"]] == ["crashed", "restarted"]


def test_too_many_crashes_in_the_window_give_up_on_that_node_only():
    sup = Supervisor(RestartPolicy(initial_backoff_s=0.1, burst=3, interval_s=10.0))
    t = 0.0
    for _ in range(3):
        assert sup.crashed("r3", -9, now=t).kind == "crashed"
        t += 1.0
        sup.restarted("r3")
    assert sup.crashed("r3", 1, now=t).kind == "gave-up"  # the 4th within 10 s
    assert not sup.waiting("r3") and sup.due(now=t + 100) == []
    assert "4 crashes within 10 s" in sup.given_up()["r3"]
    assert sup.crashed("r1", -9, now=t).kind == "crashed"  # the others are still looked after
    assert sup.report()["crashes"] == 5


def test_crashes_outside_the_window_do_not_count():
    sup = Supervisor(RestartPolicy(initial_backoff_s=0.1, burst=2, interval_s=10.0))
    for t in (0.0, 11.0, 22.0, 33.0):
        assert sup.crashed("r1", -11, now=t).kind == "crashed"
        sup.restarted("r1")
    assert sup.given_up() == {}


def test_bad_configuration_is_given_up_at_once():
    sup = Supervisor()
    event = sup.crashed("laptop", 2, now=0.0)
    assert event.kind == "gave-up" and "bad configuration" in event.detail
    assert sup.due(now=1e9) == []


def test_the_live_table_and_the_status_line_show_what_the_supervisor_did():
    from rich.console import Console

    from autopower.cli.live_table import render
    from autopower.launch.summary import status_line

    sup = Supervisor(RestartPolicy(burst=1))
    sup.crashed("r2", -9, now=0.0)
    sup.restarted("r2")
    sup.crashed("r2", -9, now=1.0)
    snap = {"scenario": "paper-fig7", "robots": {}, "supervision": {**sup.report(), "down": []}}
    console = Console(record=True, width=200)
    console.print(render(snap, 5.0))
    text = console.export_text()
    assert "supervisor: 2 crash(es), restarts r2 1x; GAVE UP on r2 (2 crashes within 60 s" in text
    assert "r2 restarted: restart 1" in text and "r2 gave-up" in text
    assert "GAVE UP on r2" in status_line(snap, 5.0)
