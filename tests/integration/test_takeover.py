"""A base station that takes over a running team: real processes, real Zenoh (mutual TLS) on 127.0.0.1.

The base station is killed with SIGKILL in the middle of a mission and a new base station process
is started for the same team, the way systemd (``Restart=on-failure``) or `up`'s supervision
would start it: the same command line. The robots keep running meanwhile (their subgroup round
takes over the stages that ran on the laptop). The new base station must adopt what runs and
go on with the mission's clock; the operator's outputs must resume within 2 s of it coming up,
none lost and none delivered twice across the two base stations.

Then two base stations at once: a second one started on "another host" (its own state
directory, its own port, connecting to the robots) takes over; the older one sees the newer
one's plans and steps down.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time

import pytest

from autopower.basestation.operator import TEAMS_DIR, OperatorClient, state_dir
from autopower.cli.options import build_scenario
from autopower.launch.localhost import Child, LocalTeam, TeamSpec, _die_with_parent, endpoint
from autopower.node.sink_store import SinkStore
from tests.integration.runtime_helpers import reference_digest, sinks_of, wait_for

pytestmark = pytest.mark.slow

SPEED = 10.0
OPERATOR_CHAINS = ("Blob-2", "Blob-3")  # their sink is the operator, at the base station


def restart(team: LocalTeam, name: str, argv: list[str], env: dict | None = None) -> Child:
    """Start a base station process with ``argv`` (as the launcher would), its log apart."""
    log_path = team.log_dir / f"{name}.log"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                process_group=0, preexec_fn=_die_with_parent,
                                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})})
    return Child(name, proc, log_path)


def operator_received(snap: dict) -> dict[str, int]:
    sinks = (snap.get("basestation") or {}).get("sinks") or {}
    return {c: sinks[c]["received_total"] for c in OPERATOR_CHAINS if c in sinks}


def no_gaps(snap: dict) -> bool:
    sinks = sinks_of(snap)
    return len(sinks) == 5 and all(s["contiguous"] == s["max_seq"] + 1 for s in sinks.values())


def test_a_new_base_station_takes_over_after_sigkill(tmp_path):
    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=SPEED, auto_replan=False, lease_ms=1000, log_dir=tmp_path)
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        before = wait_for(team, lambda s: all(v >= 40 for v in operator_received(s).values())
                          and len(operator_received(s)) == 2, 30, "the operator's first outputs")
        old = team.children["laptop"]
        team.expected_exits.add("laptop")
        os.kill(old.proc.pid, signal.SIGKILL)
        old.proc.wait(timeout=5)
        # what the killed base station had acknowledged to the producers, as it kept it (the journal is
        # written with each status: outputs taken in after the last one are resent by custody)
        kept = SinkStore(state_dir() / TEAMS_DIR / team.team / "sinks.json").load(before["mission"]["epoch_unix"])
        delivered = {c: kept[c].received_total for c in OPERATOR_CHAINS}
        assert all(delivered[c] > 0 for c in OPERATOR_CHAINS), delivered
        time.sleep(2.0)  # the robots carry on without a base station for a while

        new = restart(team, "laptop-restarted", list(old.proc.args))
        team.children["laptop"] = new
        team.expected_exits.discard("laptop")
        # poll the operator's outputs as they come back (the snapshot is the base station's answer)
        resumed_unix, snap = None, {}
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            team.check_children()
            try:
                snap = team.snapshot(timeout_s=1.0)
            except Exception:
                continue
            got = operator_received(snap)
            if len(got) == 2 and all(got[c] > delivered[c] for c in OPERATOR_CHAINS):
                resumed_unix = time.time()
                break
            time.sleep(0.02)
        assert resumed_unix is not None, f"the operator's outputs did not resume; last snapshot events: {snap.get('events')}"
        takeover = snap["takeover"]
        assert takeover is not None, "the new base station started a mission of its own instead of taking over"
        adopt_s = takeover["adopted_unix"] - takeover["up_unix"]
        resume_s = resumed_unix - takeover["up_unix"]
        print(f"\ntakeover: adopted {adopt_s:.3f} s after the new base station came up; operator outputs resumed "
              f"{resume_s:.3f} s after it came up")
        assert resume_s < 2.0, f"operator outputs resumed {resume_s:.2f} s after the base station came up"
        assert adopt_s < spec.status_period_s * 2 + spec.lease_ms / 1000 + 0.5

        # one mission clock: the team's, not a new zero
        assert snap["mission"] == before["mission"]
        assert snap["incarnation"] == before["incarnation"] + 1
        assert snap["epoch"] > before["epoch"]  # epochs go on, they do not restart at 0
        expected_t = (time.time() - before["mission"]["epoch_unix"]) * SPEED
        assert abs(snap["t_virtual"] - expected_t) < 1.0 * SPEED, (snap["t_virtual"], expected_t)
        assert takeover["mission_t_s"] > before["t_virtual"]

        # the robots run the new base station's plans, and nothing was lost or delivered twice
        settled = wait_for(team, lambda s: s["ready"] and no_gaps(s) and all(
            v["status"]["plan_incarnation"] == s["incarnation"] and v["status"]["plan_epoch"] == s["epoch"]
            # a robot names its mission only to a base station that does not run its plan
            and v["status"]["mission"] in (None, s["mission"]) for v in s["robots"].values())
            and all(v > delivered[c] + 40 for c, v in operator_received(s).items()), 30,
            "every robot on the new base station's plan, every sink without a gap")
        for chain, stats in sinks_of(settled).items():
            assert stats["duplicates_total"] == 0, (chain, stats)
            assert stats["stale"] == 0, (chain, stats)
        for chain in OPERATOR_CHAINS:  # every output 0..n-1 once, in order, across both base stations
            stats = settled["basestation"]["sinks"][chain]
            assert stats["contiguous"] > delivered[chain]
            assert stats["digest"] == reference_digest(scenario, chain, stats["contiguous"]), chain
        log = new.log_path.read_text()
        assert "took over a running team" in log and "sinks go on from" in log
        codes = team.stop()
        assert codes.get("laptop-restarted") == 0, (codes, team.log_dir)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_base_stations_at_once_the_older_steps_down(tmp_path):
    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=SPEED, auto_replan=False, lease_ms=1000, log_dir=tmp_path)
    with LocalTeam(spec, scenario) as team:
        first = team.wait_ready(60)
        old = team.children["laptop"]
        # the same base station on "another host": its own port and state directory, reaching the robots
        argv = list(old.proc.args)
        second_endpoint = endpoint(free_port(), scheme=team.scheme)
        argv[argv.index("--listen") + 1] = second_endpoint
        for robot in team.nodes[1:]:
            argv += ["--connect", endpoint(team.ports[robot], scheme=team.scheme)]
        second = restart(team, "laptop-second", argv, env={"AUTOPOWER_STATE_DIR": str(tmp_path / "other-host")})
        try:
            rc = old.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the older base station did not step down within 30 s; its log ends:\n{old.tail()}")
        team.expected_exits.add("laptop")
        assert rc == 0, old.tail()  # stepping down is not a failure: systemd must not restart it
        old_log = old.log_path.read_text()
        assert "stepping down: another base station runs team" in old_log, old.tail()
        assert f"(incarnation {first['incarnation'] + 1}, ours {first['incarnation']})" in old_log
        assert second.proc.poll() is None, second.tail()
        team.children["laptop-second"] = second

        # the robots follow the newer one; the mission clock is still the first one's
        with OperatorClient(team.team, settings=team.identities.operator_settings(second_endpoint)) as client:
            deadline, snap = time.monotonic() + 20, {}
            while time.monotonic() < deadline:
                snap = client.snapshot(timeout_s=5.0)
                if snap["ready"] and all((v["status"] or {}).get("plan_incarnation") == snap["incarnation"]
                                         for v in snap["robots"].values()):
                    break
                time.sleep(0.1)
        assert snap["incarnation"] == first["incarnation"] + 1
        assert snap["mission"] == first["mission"]
        for name, info in snap["robots"].items():
            assert info["status"]["plan_incarnation"] == snap["incarnation"], name
            assert info["status"]["mission"] in (None, first["mission"]), name  # named only to one behind
        assert all(s["duplicates_total"] == 0 for s in sinks_of(snap).values())
        second_log = second.log_path.read_text()
        assert "took over a running team" in second_log
        assert snap["takeover"]["previous"]["leader"] == first["leader"]  # it says whom it took over from
