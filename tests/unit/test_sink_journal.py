"""Outputs a sink delivered just before it was killed are not lost from the recording.

A testbed demo (2026-11-25) killed the base station between the commit of its sinks' notes and the
flush of their recording: 10 Blob-2 and 10 Blob-3 outputs the operator had were missing from the
recording, and the replay called them lost. The notes come first on purpose (the other order makes
the same window deliver duplicates to the operator), so the restarted sink names what its last
commit noted (`SinkStore.last_batch`), the recorder logs it, and the replay counts it apart.
"""

from __future__ import annotations

import zlib

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.ports import NodeStores, SinkListener
from autopower.node.runtime import NodeRuntime
from autopower.node.sequencing import SinkLedger
from autopower.node.sink_store import SinkStore
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam


def _commit(store: SinkStore, ledger: SinkLedger, seqs, mission: float = 100.0) -> None:
    """Outputs taken in, then the commit before the status that acknowledges them."""
    for seq in seqs:
        data = b"out%d" % seq
        assert ledger.record(0, seq, data=data)
        store.keep(mission, {"Blob-2": ledger}, "Blob-2", 0, seq, zlib.crc32(data))
    store.commit()


def test_the_last_commit_is_what_a_restarted_sink_names(tmp_path):
    path = tmp_path / "sinks.json"
    store, ledger = SinkStore(path), SinkLedger()
    _commit(store, ledger, [0, 1])  # the first commit of a mission writes a snapshot
    _commit(store, ledger, [2, 3, 4])
    _commit(store, ledger, [5, 6])
    restarted = SinkStore(path)
    assert restarted.load(100.0)["Blob-2"].contiguous == 7
    assert restarted.last_batch == [("Blob-2", 0, 5), ("Blob-2", 0, 6)]  # 2-4 were flushed before 5 came


def test_a_commit_torn_by_the_kill_is_the_last_batch(tmp_path):
    path = tmp_path / "sinks.json"
    store, ledger = SinkStore(path), SinkLedger()
    _commit(store, ledger, [0])
    _commit(store, ledger, [1, 2])
    with open(path, "ab") as f:  # killed while the next commit was written: one whole note, one torn
        f.write(b'["Blob-2",0,3,%d]\n["Blob-2",0,4' % zlib.crc32(b"out3"))
    restarted = SinkStore(path)
    assert restarted.load(100.0)["Blob-2"].contiguous == 4
    assert restarted.last_batch == [("Blob-2", 0, 3)]


def test_a_journal_without_markers_names_every_note_after_its_snapshot(tmp_path):
    """A file an older version wrote (no commit markers): every note may be the last commit's."""
    path = tmp_path / "sinks.json"
    path.write_text('{"mission_epoch_unix": 100.0}\n{"sinks": {}}\n["Blob-2",0,0,1]\n["Blob-2",0,1,2]\n')
    store = SinkStore(path)
    assert store.load(100.0)["Blob-2"].contiguous == 2
    assert store.last_batch == [("Blob-2", 0, 0), ("Blob-2", 0, 1)]
    assert SinkStore(path).last_batch == []  # nothing before a load


def test_a_restarted_sink_says_what_its_last_commit_delivered(tmp_path):
    team = SimTeam(load_scenario("paper-fig7"), config=CoordinatorConfig(speed=1.0, auto_replan=False),
                   stores={"laptop": NodeStores(sink_store=SinkStore(tmp_path / "sinks.json"))})
    team.join()
    old = team.nodes["laptop"]
    team.run_until(20.0)
    old.sinking.store.commit()
    team.run_until(22.0)
    delivered = {c: (l.run, l.contiguous) for c, l in old.sinks.items()}
    old.sinking.store.commit()  # the last status before the kill; then killed before the flush
    rt = NodeRuntime(node="laptop", scenario=team.scenario, bus=team.hub.bus("laptop-again"), keys=team.keys,
                     make_component=FakeComponent, make_source=FakeSource, clock_factory=lambda m: team.clock,
                     stores=NodeStores(sink_store=SinkStore(tmp_path / "sinks.json")))
    named = []
    rt.listen(SinkListener(sink_journal=lambda chain, run, seq: named.append((chain, run, seq))))
    rt.on_plan(old.plan)
    assert named, "the restarted sink named nothing"
    # each named output is one the old sink had delivered in its last two seconds, none twice
    assert len(set(named)) == len(named)
    for chain, run, seq in named:
        assert run == delivered[chain][0] and seq < delivered[chain][1]
    assert {c for c, _, _ in named} == {c for c in delivered if delivered[c][1] > 0}


def test_the_replay_takes_outputs_a_killed_sink_delivered_as_delivered(tmp_path):
    from types import SimpleNamespace

    from autopower.recording.merge import merge_run
    from autopower.recording.recorder import Recorder
    from autopower.recording.replay import load, summarize

    t = [0.0]
    run_dir = tmp_path / "run-7"
    sink = Recorder.open(run_dir, "laptop", clock=lambda: t[0])
    listeners = []
    sink.attach(SimpleNamespace(listen=listeners.append))
    runtime = listeners[0]  # what the runtime tells the recorder (`SinkListener`)
    sink.telemetry.battery(0.0, "r1", 100.0)
    for seq in (*range(0, 10), *range(15, 20)):  # 10-14 delivered, their recording died with the process
        t[0] += 0.5
        sink.on_output("Blob-2", 0, seq, b"")
    for seq in (10, 11, 12, 13, 14, 15):  # the restarted sink's journal: 15 was recorded after all
        runtime.sink_journal("Blob-2", 0, seq)
    sink.telemetry.battery(10.0, "r1", 90.0)
    sink.close()
    s = summarize(load(merge_run(run_dir)))
    o = s["outputs"]
    assert (o["lost"], o["unrecorded"], o["duplicated"]) == (0, 5, 0)
    assert (o["chains"]["Blob-2"]["lost"], o["chains"]["Blob-2"]["unrecorded"]) == (0, 5)
    detail = next(i["detail"] for i in s["invariants"] if i["name"] == "every output exactly once at its sink")
    assert "5 delivered by a sink killed before it flushed their recording" in detail


_KILLED_SINK = """
import os, signal, sys
from autopower.recording.recorder import Recorder
t = [0.0]
sink = Recorder.open(sys.argv[1], "r2", clock=lambda: t[0], flush_every_s=0.0)
sink.telemetry.battery(0.0, "r2", 100.0)
for seq in range(0, 5):
    t[0] += 0.5
    sink.on_output("Loc-2", 0, seq, b"")
sink.flush_outputs()  # the sink noted 0-4: written with that commit
for seq in range(5, 8):  # taken in after the last commit
    t[0] += 0.5
    sink.on_output("Loc-2", 0, seq, b"")
    sink.on_held_dropped("Blob-2", 0, seq)  # other records, each with the timed flush due
sink.telemetry.flush()
os.kill(os.getpid(), signal.SIGKILL)  # before the next commit
"""


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # a killed process writes none
def test_an_output_taken_in_after_the_last_commit_dies_unrecorded_with_a_killed_sink(tmp_path):
    """Issue 30 (CI on 31847dc): r2, the Loc-2 sink, was SIGKILLed and restarted with its saved
    ledger; the laptop resent results 29-31, which r2 had taken in after its last commit, and the
    new sink delivered them again. The old process's timed flush had already written one of them to
    the recording: outputs are written with the sink's commits only (`Recorder.flush_outputs`), so
    what custody resends is recorded once, by the restarted sink."""
    import subprocess
    import sys

    from autopower.recording.merge import merge_run
    from autopower.recording.recorder import output_path
    from autopower.recording.replay import load

    run_dir = tmp_path / "run-9"
    done = subprocess.run([sys.executable, "-c", _KILLED_SINK, str(run_dir)], capture_output=True, timeout=60)
    assert done.returncode == -9, done.stderr.decode()
    recording = load(merge_run(run_dir))
    assert "components/Blob-2/run/0/held_dropped" in recording.scalars, "the timed flush wrote nothing: the test proves nothing"
    _, seqs = recording.scalars[output_path("Loc-2", 0)]
    assert sorted(seqs) == [0, 1, 2, 3, 4]
