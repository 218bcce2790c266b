"""Stage worker processes, live: real processes, real Zenoh, the base station with ``--stage-workers on``.

Both motion detectors of the worked example run on the base station, each in its own worker
process. Motion-2's detector spins for ever from its 10th frame: its worker is SIGKILLed, the
stage is reported failed, and Motion-1 (the same node, another worker) goes on, exactly once.
Then Motion-1 moves from the worker-hosting base station to a robot with its state (its outputs
stay those of a run that never moved).

Then a crash: the base station of paper-fig7 (all five stages in workers) is SIGKILLed while Blob-2's
worker holds the inputs that piled up behind a slow run; the robots take the stages over, a new base
station takes the team over, and the operator gets every blob report exactly once.
"""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from autopower.basestation.operator import TEAMS_DIR, state_dir
from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.node.sink_store import SinkStore
from autopower.protocol import MigrateCommand
from tests.integration.runtime_helpers import reference_digest, sinks_of, wait_for
from tests.integration.test_plugin_components import assert_exactly_once_and_like_offline, plugin_path, with_component  # noqa: F401
from tests.integration.test_takeover import OPERATOR_CHAINS, no_gaps, restart

SPIN_AT_FRAME = 10


def children_of(pid: int) -> set[int]:
    out = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as f:
                    ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if ppid == pid:
                out.add(int(entry))
    return out


def test_a_spinning_component_is_killed_the_other_stage_runs_on_and_a_stage_moves_with_its_state(
        plugin_path, tmp_path):  # noqa: F811
    path = with_component(tmp_path, "Motion-2", "Spinner", "tests.integration.faulty_components:SpinsAtTen")
    spec = TeamSpec(scenario=str(path), speed=10.0, auto_replan=False, log_dir=tmp_path / "logs",
                    pins=("Motion-1=laptop", "Motion-2=laptop"), stage_workers="on")
    team = LocalTeam(spec, build_scenario(str(path)))
    team.__enter__()
    try:
        team.wait_ready(60)
        base_pid = team.children["laptop"].proc.pid
        wait_for(team, lambda s: len(children_of(base_pid)) == 1, 30, "the base station's worker zygote")
        [zygote] = children_of(base_pid)  # the worker factory: one per node
        wait_for(team, lambda s: len(children_of(zygote)) == 2 and sinks_of(s).get("Motion-1", {}).get(
            "contiguous", 0) >= 5, 30, "both stages running in workers")
        # the hang verdict for a call that keeps computing: 10 limits of 2 s (3 periods at x10 < 2 s)
        snap = wait_for(team, lambda s: "Motion-2" in s.get("failed_stages", {}), 60, "Motion-2 to be killed")
        failed = snap["failed_stages"]["Motion-2"]
        assert "hung" in failed and "still running" in failed and "its worker process was killed" in failed, failed
        assert "Motion-2" in snap["disabled"]
        assert sinks_of(snap)["Motion-2"]["contiguous"] == SPIN_AT_FRAME  # every frame before it, none after
        deadline = time.monotonic() + 10
        while len(children_of(zygote)) != 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(children_of(zygote)) == 1  # killed: only Motion-1's worker is left, nothing spins
        before = sinks_of(snap)["Motion-1"]["contiguous"]
        snap = wait_for(team, lambda s: sinks_of(s)["Motion-1"]["contiguous"] >= before + 20, 20, "Motion-1 to go on")
        assert team.children["laptop"].proc.poll() is None
        # Motion-1 leaves the worker-hosting base station for r1, with its state (the previous frame)
        assert team.client.request(MigrateCommand(stage="Motion-1", to_node="r1")).ok
        wait_for(team, lambda s: s["placement"]["Motion-1"] == "r1" and s["ready"], 20, "Motion-1 on r1")
        moved = sinks_of(team.snapshot())["Motion-1"]["contiguous"]
        snap = wait_for(team, lambda s: sinks_of(s)["Motion-1"]["contiguous"] >= moved + 20, 30, "Motion-1 on r1")
        assert sinks_of(snap)["Motion-1"]["duplicates_total"] == 0
        assert_exactly_once_and_like_offline(team.scenario, {**snap, "basestation": {
            "sinks": {"Motion-1": sinks_of(snap)["Motion-1"]}}, "robots": {}})
        assert len(children_of(zygote)) == 0  # its worker went with it
    finally:
        codes = team.stop()
        assert all(c == 0 for c in codes.values()), (codes, team.log_dir)


FIG7 = Path(__file__).resolve().parents[2] / "autopower" / "scenarios" / "paper-fig7.toml"


def fig7_with_slow_blob2(tmp_path: Path) -> Path:
    """paper-fig7 (same name: same chain seeds, same frames) with Blob-2's finder slow on every 100th run."""
    head, sep, tail = FIG7.read_text().partition('name = "Blob-2"')
    assert sep and 'component = "Blob"' in tail
    text = head + sep + tail.replace('component = "Blob"', 'component = "SlowBlob"', 1)
    text = text.replace("state_bytes = { Loc = 32197, Blob = 1 }", "state_bytes = { Loc = 32197, Blob = 1, SlowBlob = 1 }")
    assert "SlowBlob = 1" in text
    text += """
[components.SlowBlob]
implementation = "tests.integration.faulty_components:SlowEveryHundred"
source = "autopower.chains.camera:CameraSource"
latency_s = { sitsang = 0.115, laptop = 0.01048 }
"""
    path = tmp_path / "fig7-slow-blob2.toml"
    path.write_text(text)
    return path


@pytest.mark.slow
def test_a_base_station_killed_while_its_workers_hold_inputs_loses_and_repeats_no_output(plugin_path, tmp_path):  # noqa: F811
    from tests.integration.faulty_components import SLOW_EVERY  # importable with the plug-in path

    path = fig7_with_slow_blob2(tmp_path)
    spec = TeamSpec(scenario=str(path), speed=10.0, auto_replan=False, lease_ms=1000, log_dir=tmp_path / "logs",
                    stage_workers="on")
    with LocalTeam(spec, build_scenario(str(path))) as team:
        team.wait_ready(60)
        snap = wait_for(team, lambda s: s["placement"].get("Blob-2") == "laptop" and s["ready"], 30,
                        "Blob-2 on the base station")
        base = team.children["laptop"]
        # Blob-2's worker is in a slow run (2 s): output K-1 is out, K is not, and r2 keeps producing
        # (40 frames a second), so the frames after K pile up in the worker. Kill it then.
        stalled, seen = None, []
        deadline = time.monotonic() + 90
        while stalled is None and time.monotonic() < deadline:
            team.check_children()
            snap = team.snapshot()
            blob = sinks_of(snap).get("Blob-2", {})
            k = blob.get("contiguous", 0)
            seen.append((k, blob.get("max_seq")))
            if k and k % SLOW_EVERY == 0 and blob["max_seq"] == k - 1:
                stalled = k
            else:
                time.sleep(0.05)
        assert stalled is not None, f"never caught Blob-2's worker in its slow run: (contiguous, max_seq) {seen[-40:]}"
        # 0.6 s into the 2 s run: ~24 more frames reached the worker, a status (every 0.5 s) went out
        time.sleep(0.6)
        team.expected_exits.add("laptop")
        os.kill(base.proc.pid, signal.SIGKILL)
        base.proc.wait(timeout=5)
        kept = SinkStore(state_dir() / TEAMS_DIR / team.team / "sinks.json").load(snap["mission"]["epoch_unix"])
        # what the killed base station had delivered to the operator: nothing from the slow run's frame on
        assert kept["Blob-2"].contiguous <= stalled, (kept["Blob-2"].contiguous, stalled)
        time.sleep(2.0)  # the robots carry on without a base station (they take the stages over)

        new = restart(team, "laptop-restarted", list(base.proc.args))
        team.children["laptop"] = new
        team.expected_exits.discard("laptop")
        settled = wait_for(team, lambda s: s["ready"] and no_gaps(s) and all(
            sinks_of(s)[c]["contiguous"] > kept[c].contiguous + 2 * SLOW_EVERY for c in OPERATOR_CHAINS), 120,
            "every sink without a gap, the operator's chains well past the kill")
        for chain, stats in sinks_of(settled).items():
            assert stats["duplicates_total"] == 0, (chain, stats)
        reference = build_scenario("paper-fig7")  # the slow finder's outputs are the finder's
        for chain in OPERATOR_CHAINS:  # every blob report 0..n-1 once, in order, across the kill
            stats = settled["basestation"]["sinks"][chain]
            assert stats["received_total"] == stats["contiguous"] and stats["given_up_total"] == 0, (chain, stats)
            assert stats["digest"] == reference_digest(reference, chain, stats["contiguous"]), chain
        codes = team.stop()
        assert codes.get("laptop-restarted") == 0, (codes, team.log_dir)
