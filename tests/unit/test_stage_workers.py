"""Stage worker processes (`autopower.node.workers`): a stage's component in a process of its own.

The protocol: runs handed over asynchronously come back in order, one at a time; what a component
raises, returns or does to its process comes back as the stage's failure; a hung call's worker
is killed (no thread left spinning); a state exported from one worker imports into another; the
queue in front of a worker is bounded. Then a whole team (`SimTeam`, real worker processes) with
every node's stages in workers: outputs exactly once, a migration carries the state, and a
spinning component is killed while the node's other stage goes on.

The components below are module-level: a worker imports them by name (``tests.unit.test_stage_workers``).
"""

from __future__ import annotations

import os
import time

import msgpack
import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node import guard
from autopower.node.ports import SinkListener
from autopower.node.sequencing import in_ranges
from autopower.node.workers import (
    STAGE_QUEUE,
    WINDOW,
    ComponentHung,
    StageWorker,
    WorkerComponent,
    WorkerCrashed,
    Zygote,
    recipe_for,
    worker_of,
)
from autopower.protocol import MigrateCommand
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam

FC = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}


class Faulty(FakeComponent):
    """Raises at seq 3, exits its process at seq 4, spins at seq 5, blocks at seq 6 (by robot)."""

    def run(self, payload):
        seq = msgpack.unpackb(payload)[1]
        if self.robot == "raise" and seq == 3:
            raise KeyError("no such blob")
        if self.robot == "exit" and seq == 3:
            os._exit(7)
        if self.robot == "spin" and seq >= 2:
            while True:
                pass
        if self.robot == "block" and seq >= 2:
            time.sleep(3600)
        if self.robot == "slow":
            time.sleep(0.2)
        if self.robot == "str":
            return "not bytes"
        if self.robot == "env":
            return ",".join(sorted(os.environ)).encode()
        return super().run(payload)


def make(kind, robot, seed):
    """The factory a worker imports: Faulty for the robots named after a fault, else FakeComponent."""
    return Faulty(kind, robot, seed)


class SpinsFromSeq2(FakeComponent):
    def run(self, payload):
        if msgpack.unpackb(payload)[1] >= 2:
            while True:
                pass
        return super().run(payload)


class Slow(FakeComponent):
    def run(self, payload):
        time.sleep(SLOW_RUN_S)
        return super().run(payload)


SLOW_RUN_S = 0.1


def make_slow_blob2(kind, robot, seed):
    """Blob-2 (r2's blob finder) takes `SLOW_RUN_S` a run: its worker holds inputs for a while."""
    return (Slow if (kind, robot) == ("Blob", "r2") else FakeComponent)(kind, robot, seed)


def make_spinning_blob2(kind, robot, seed):
    """Blob-2 (r2's blob finder) spins from its seq 2; everything else counts."""
    return (SpinsFromSeq2 if (kind, robot) == ("Blob", "r2") else FakeComponent)(kind, robot, seed)


class BlobPageFaults:
    """The blob finder, returning the page faults its run took (what its worker's malloc costs)."""

    def __init__(self, robot, seed):
        from autopower.chains.blobfinder import BlobFinder

        self.finder = BlobFinder(robot)

    def run(self, payload):
        import resource

        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        self.finder.run(payload)
        return msgpack.packb(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)


@pytest.fixture
def zygote():
    z = Zygote()
    yield z
    z.close()


def worker(zygote, robot="r1", timeout_s=30.0):
    w = StageWorker(zygote, None)
    return w, WorkerComponent(w, recipe_for(make, "Blob", robot, 1, None), timeout_s=timeout_s)


def frame(robot, seq):
    return msgpack.packb([robot, seq])


def finish(w, timeout_s=30.0):
    """Every result of what was handed to ``w``, in the order they came back."""
    out, deadline = [], time.monotonic() + timeout_s
    while w.inflight is not None and time.monotonic() < deadline:
        done = w.poll(0.1)
        if done is not None:
            out.append(done)
    return out


def gone(pid: int, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.02)
    return False


def test_runs_handed_over_at_once_come_back_in_order_and_the_state_moves(zygote):
    w, component = worker(zygote)
    for seq in range(40):  # the loop does not wait: all 40 are handed over (a window sent, the rest queued)
        w.submit(seq, frame("r1", seq))
    done = finish(w)
    assert [item for item, _ in done] == list(range(40))
    assert [msgpack.unpackb(reply[2]) for _, reply in done] == [[s, s + 1] for s in range(40)]
    assert all(reply[0] == "ok" and reply[1] >= 0.0 for _, reply in done)  # the run's own compute time
    state = component.export_state()
    w2, moved = worker(zygote)
    moved.import_state(state)
    assert msgpack.unpackb(moved.run(frame("r1", 40))) == [40, 41]  # the count went on in the other process
    component.close()
    moved.close()
    assert gone(w.pid) and gone(w2.pid)


def test_what_a_component_raises_returns_or_does_to_its_process_comes_back(zygote):
    w, _ = worker(zygote, "raise")
    for seq in range(5):
        w.submit(seq, frame("raise", seq))
    replies = [reply for _, reply in finish(w)]
    assert replies[3] == ["err", "KeyError", "'no such blob'"]
    assert [r[0] for r in replies] == ["ok", "ok", "ok", "err", "err"]  # seq 4: "expected seq 4" after the gap
    w, component = worker(zygote, "str")
    w.submit(0, frame("str", 0))
    assert finish(w)[0][1] == ["bad", "str"]
    with pytest.raises(Exception) as raised:  # raised in the worker, named as in-process
        worker(zygote, "raise")[1].import_state(b"\xc1")
    assert type(raised.value).__name__ in ("ExtraData", "FormatError", "UnpackValueError", "ValueError")
    w, _ = worker(zygote, "exit")
    for seq in range(6):
        w.submit(seq, frame("exit", seq))
    done = finish(w)
    assert [item for item, _ in done] == [0, 1, 2, 3] and done[3][1] is None  # None: the process ended
    assert gone(w.pid)
    with pytest.raises(WorkerCrashed):
        WorkerComponent(w, recipe_for(make, "Blob", "r1", 1, None), timeout_s=1.0)


@pytest.mark.parametrize("robot, how, spin_factor, within", [("spin", "still running", 4, (0.8, 3.0)),
                                                              ("block", "blocked", 10, (0.7, 2.0))])
def test_a_hung_run_gets_its_worker_killed(zygote, monkeypatch, robot, how, spin_factor, within):
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.5)  # the product's: a starved spinner still gets CPU in 0.5 s
    monkeypatch.setattr(guard, "SPIN_FACTOR", spin_factor)
    w, component = worker(zygote, robot)
    assert msgpack.unpackb(component.run(frame(robot, 0))) == [0, 1]
    w.submit(1, frame(robot, 1))
    assert finish(w)[0][1][0] == "ok"
    w.submit(2, frame(robot, 2))
    started, verdict = time.monotonic(), None
    while verdict is None and time.monotonic() - started < 10:
        time.sleep(0.05)
        verdict = w.run_hung(0.2, time.monotonic())
    assert verdict is not None and f"({how}; limit 0.2 s)" in verdict
    assert within[0] <= time.monotonic() - started < within[1]
    w.kill()
    assert gone(w.pid)  # killed: nothing keeps spinning (a thread could not be killed)
    # a synchronous call that hangs is killed the same way
    w, component = worker(zygote, robot, timeout_s=0.2)
    component.run(frame(robot, 0))
    component.run(frame(robot, 1))
    with pytest.raises(ComponentHung, match=how):
        component.run(frame(robot, 2))
    assert gone(w.pid)


def test_a_worker_says_how_much_room_it_has_and_what_it_still_holds(zygote):
    w, _ = worker(zygote, "slow")
    assert w.room() == WINDOW + STAGE_QUEUE
    for seq in range(WINDOW + STAGE_QUEUE):
        w.submit(seq, frame("slow", seq))
    assert w.room() == 0  # the node refuses the next input before its gate takes it (`Frames._no_room`)
    assert len(w.sent) == WINDOW and list(w.outstanding()) == list(range(WINDOW + STAGE_QUEUE))
    assert w.poll(5.0)[0] == 0  # one result taken: one more fits, and the oldest is no longer held
    assert w.room() == 1 and next(iter(w.outstanding())) == 1
    w.kill()
    assert list(w.outstanding()) == []


def test_a_worker_inherits_no_secrets(zygote, monkeypatch):
    monkeypatch.setenv("AUTOPOWER_TEST_SECRET", "hunter2")
    monkeypatch.setenv("ZENOH_CONFIG", "/secret/zenoh.json5")
    z = Zygote()  # started after the variables were set
    try:
        w = StageWorker(z, None)
        component = WorkerComponent(w, recipe_for(make, "Blob", "env", 1, None), timeout_s=30.0)
        names = component.run(frame("env", 0)).decode().split(",")
    finally:
        z.close()
    assert "AUTOPOWER_TEST_SECRET" not in names and "ZENOH_CONFIG" not in names
    assert "PYTHONPATH" in names and "OPENBLAS_NUM_THREADS" in names


def test_a_worker_keeps_its_runs_memory_instead_of_faulting_it_in_each_run(zygote):
    """glibc gave a blob finder's 0.6 MB temporaries back to the kernel after every run: ~200 page
    faults and 0.5 ms of system time a run (bench/bench_stage_worker_cpu.py: 1.3 ms of CPU in a
    worker against 0.8 ms in-process). A worker's malloc keeps them (`workers._MALLOC`)."""
    from autopower.chains import make_source

    source = make_source("Blob", "r2", 1)
    w = StageWorker(zygote, None)
    component = WorkerComponent(w, ["class", "tests.unit.test_stage_workers:BlobPageFaults", "r2", 1], timeout_s=60.0)
    faults = [msgpack.unpackb(component.run(source.produce(seq))) for seq in range(25)]
    component.close()
    assert sum(faults[5:]) / 20 < 20, faults  # after the first runs: none to speak of (~200 each before)


def test_a_factory_a_worker_cannot_import_runs_in_process():
    from autopower import chains

    assert recipe_for(lambda kind, robot, seed: None, "Blob", "r1", 1, None) is None
    assert recipe_for(chains.make_component, "Blob", "r1", 1, None) == ["registry", "Blob", "r1", 1, None]
    assert recipe_for(make, "Blob", "r1", 1, None) == ["call", "tests.unit.test_stage_workers:make", "Blob", "r1",
                                                       1, None]


# ---- a whole team with its stages in workers --------------------------------------------------------


def team_in_workers(factory, *, speed=1.0, pins=None) -> SimTeam:
    team = SimTeam(load_scenario("paper-fig7"),
                   config=CoordinatorConfig(speed=speed, media=FC, auto_replan=False, pins=pins or {}),
                   fake=True, speed=speed,
                   node_kwargs={node: {"make_component": factory, "make_source": FakeSource, "stage_workers": True}
                                for node in load_scenario("paper-fig7").node_names()})
    return team


def settle(team: SimTeam, until, timeout_s: float = 30.0) -> None:
    """Collect the workers' results (wall time passes, virtual time does not) until ``until()``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for rt in team.nodes.values():
            if rt.components.has_workers:
                rt.components.collect_results()
                rt.components.check_workers()
        team.pump()
        if until():
            return
        time.sleep(0.02)
    raise AssertionError("the team did not settle")


def idle(team: SimTeam) -> bool:
    return all(getattr(worker_of(h.component), "inflight", None) is None
               for rt in team.nodes.values() for h in rt.hosted.values())


def close(team: SimTeam) -> None:
    for rt in team.nodes.values():
        rt.components.close()


def outputs_of(team: SimTeam) -> dict[str, list[tuple[int, bytes]]]:
    out: dict[str, list[tuple[int, bytes]]] = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: out.setdefault(chain, []).append((seq, data))))
    return out


def test_a_team_in_workers_delivers_exactly_once_and_migrates_with_state():
    team = team_in_workers(FakeComponent, pins={"Blob-2": "r2"})
    try:
        outputs = outputs_of(team)
        team.join()
        team.run_until(5.0)
        settle(team, lambda: idle(team))
        r2 = team.nodes["r2"]
        assert worker_of(r2.hosted["Blob-2"].component) is not None and r2.hosted["Blob-2"].runs > 0  # it ran in a worker
        co = team.coordinator
        assert co.on_operator(MigrateCommand(stage="Blob-2", to_node="r3")).ok
        team.pump()
        settle(team, lambda: co.placing.placement["Blob-2"] == "r3" and not co.placing.migrations)
        team.run_until(15.0)
        settle(team, lambda: idle(team) and all(
            len(outputs.get(c.name, [])) == team.nodes[c.source].sources[c.name].seq for c in team.scenario.chains))
        assert co.placing.migrations_done == 1 and not co.placing.aborted
        for chain in team.scenario.chains:
            produced = team.nodes[chain.source].sources[chain.name].seq
            assert sorted(seq for seq, _ in outputs[chain.name]) == list(range(produced)), chain.name
        counts = [msgpack.unpackb(data)[1] for _, data in sorted(outputs["Blob-2"])]
        assert counts == list(range(1, len(counts) + 1))  # the count went on across the move: the state moved
        assert not any(rt.hosting.failed for rt in team.nodes.values())
    finally:
        close(team)


def test_a_spinning_component_in_a_worker_is_killed_and_its_node_goes_on(monkeypatch):
    monkeypatch.setattr(guard, "HANG_MIN_WALL_S", 0.2)
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.5)  # the product's: a starved spinner still gets CPU in 0.5 s
    monkeypatch.setattr(guard, "SPIN_FACTOR", 4)
    team = team_in_workers(make_spinning_blob2, speed=10.0, pins={"Blob-2": "r2", "Loc-2": "r2"})
    try:
        outputs = outputs_of(team)
        team.join()
        team.run_until(3.0)
        r2 = team.nodes["r2"]
        pid = r2.hosted["Blob-2"].component.worker.pid
        settle(team, lambda: "Blob-2" in r2.hosting.failed, timeout_s=20.0)
        assert "hung: run(seq 2): no result after" in r2.hosting.failed["Blob-2"]
        assert "(still running; limit 0.2 s); its worker process was killed" in r2.hosting.failed["Blob-2"]
        assert gone(pid)
        assert "Blob-2" in team.coordinator.operating.disabled
        team.run_until(10.0)
        settle(team, lambda: idle(team) and len(outputs.get("Loc-2", [])) == r2.sources["Loc-2"].seq)
        assert sorted(seq for seq, _ in outputs["Loc-2"]) == list(range(r2.sources["Loc-2"].seq))
        assert r2.hosted["Loc-2"].runs == r2.sources["Loc-2"].seq
    finally:
        close(team)


def custody_of(rt, chain: str, target: int = 0) -> list[int]:
    """The seqs a producer still holds for a hop (sent, not acknowledged yet)."""
    return sorted(seq for _, seq in rt.custody.hops.get((chain, target), {}))


def drain_with_statuses(team: SimTeam, until, rounds: int = 60) -> None:
    """Statuses every half second of the team's clock (acks, resends) until ``until()``."""
    for _ in range(rounds):
        team.clock.advance(0.5)
        team.exchange_statuses()
        settle(team, lambda: True)
        if until():
            return
        time.sleep(0.05)  # the workers run on wall time
    raise AssertionError("the team did not deliver everything")


def test_inputs_in_a_worker_stay_in_their_producers_custody_and_a_crash_of_their_node_loses_none():
    """The node hosting Blob-2 in a worker dies with inputs in it: Blob-2 restarted elsewhere
    (cold, as after a crash) gets them from r2's custody; the operator sees every output once."""
    from autopower.protocol import Assign

    team = team_in_workers(make_slow_blob2, pins={"Blob-2": "r1"})
    try:
        outputs = outputs_of(team)
        team.join()
        r1, r2, r3, laptop = (team.nodes[n] for n in ("r1", "r2", "r3", "laptop"))
        team.run_until(3.0)  # 12 camera frames at once: r1's worker runs them one per 0.1 s of wall time
        settle(team, lambda: r1.hosted["Blob-2"].runs >= 2)
        team.exchange_statuses()  # r1's acknowledgements reach r2, with inputs still in the worker
        worker = r1.hosted["Blob-2"].component.worker
        held = [frame.seq for _, frame in worker.outstanding()]
        done = r1.hosted["Blob-2"].runs
        assert len(held) >= 3 and held[0] == done, (held, done)
        assert r1.hosted["Blob-2"].gate.next_seq == done + len(held)  # the gate took them all ...
        report = r1.acknowledging.consumed()["Blob-2#0"]
        assert report.next_seq == done and all(in_ranges(report.missing, s) for s in held)  # ... it acknowledges only what ran
        # so r2 still holds every one of those; what else it holds ran, its output not yet acknowledged
        # by the laptop's sink when r1 reported (in r1's memory only: a crash of r1 would take it)
        kept = set(custody_of(r2, "Blob-2"))
        assert set(held) <= kept and kept - set(held) <= set(range(done)), (sorted(kept), held, done)
        assert sorted(seq for seq, _ in outputs["Blob-2"]) == list(range(done))

        # r1 dies (SIGKILL: its worker with it, nothing more from it); Blob-2 starts on r3 without state
        r1.components.close()
        for handle in team.subscriptions.pop("r1"):
            handle.close()
        for other in ("r2", "r3", "laptop"):
            team.cut_silently("r1", other)
        r3.hosting.on_assign(Assign(stage="Blob-2", generation=10**9, chain="Blob-2", run=r2.plan.running["Blob-2"],
                            resume_seq=None))
        for rt in (r2, r3, laptop):
            rt.plan_view.override_placement({"Blob-2": "r3"}, set())
        team.run_until(6.0)
        drain_with_statuses(team, lambda: idle(team) and len(outputs.get("Blob-2", [])) == r2.sources["Blob-2"].seq)
        produced = r2.sources["Blob-2"].seq
        assert sorted(seq for seq, _ in outputs["Blob-2"]) == list(range(produced))  # none lost, none twice
        assert laptop.sinks["Blob-2"].duplicates_total == 0
        assert r3.hosted["Blob-2"].gate.catch_up_below is not None and r2.custody.resent >= len(held)
        assert "Blob-2" not in r3.hosting.failed
    finally:
        close(team)


def test_an_input_a_full_worker_cannot_take_is_refused_before_its_gate_and_resent(monkeypatch):
    """Its producer keeps it and resends it: delayed, not lost (the fake component raises on a gap)."""
    from autopower.node import workers

    monkeypatch.setattr(workers, "WINDOW", 1)
    monkeypatch.setattr(workers, "STAGE_QUEUE", 2)
    # Blob-3 on its own robot: the laptop's refusals are Blob-2's
    team = team_in_workers(make_slow_blob2, pins={"Blob-2": "laptop", "Blob-3": "r3"})
    try:
        outputs = outputs_of(team)
        team.join()
        r2, laptop = team.nodes["r2"], team.nodes["laptop"]
        team.run_until(3.0)  # 13 frames at once: room for 3 (a few more if a 0.1 s run came back meanwhile)
        hosted = laptop.hosted["Blob-2"]
        refused = laptop.counters["stage-queue-full"]
        produced = r2.sources["Blob-2"].seq
        # each frame taken by the gate (in order, or waiting behind a refused one: a run that came
        # back between two frames made room for the second) or refused before it: none taken and dropped
        waiting = set(hosted.gate.pending)
        assert refused >= 1 and hosted.gate.next_seq + len(waiting) + refused == produced
        assert "stage-queue-full" not in laptop.errors  # a refusal is not a loss
        team.exchange_statuses()
        # freed: only what has run (`is_run`). What waits behind the refused frame in the gate is
        # reported received but stays held, like the refused and those in the worker: waiting is not
        # running, and a stage that migrated before running it must get it again
        assert custody_of(r2, "Blob-2") == list(range(hosted.runs, produced)), sorted(waiting)
        drain_with_statuses(team, lambda: idle(team) and len(outputs.get("Blob-2", [])) == r2.sources["Blob-2"].seq)
        produced = r2.sources["Blob-2"].seq
        assert sorted(seq for seq, _ in outputs["Blob-2"]) == list(range(produced))
        assert [msgpack.unpackb(d)[1] for _, d in sorted(outputs["Blob-2"])] == list(range(1, produced + 1))
        assert r2.custody.resent >= refused and r2.custody.evicted == 0
        assert laptop.sinks["Blob-2"].duplicates_total == 0 and not laptop.hosting.failed
        assert sum(1 for _ in hosted.component.worker.outstanding()) == 0
    finally:
        close(team)


# ---- the option -----------------------------------------------------------------------------------


def test_auto_puts_the_base_stations_stages_in_workers_from_x20_on_4_cores(monkeypatch):
    from autopower.cli import options

    monkeypatch.setattr(options.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    want = options.stage_workers_wanted
    assert want("auto", basestation=True, speed=20.0) and want("auto", basestation=True, speed=55.0)
    assert not want("auto", basestation=True, speed=10.0)  # its loop keeps up alone: workers only cost CPU
    assert not want("auto", basestation=False, speed=100.0)  # a robot's agent
    assert want("on", basestation=False) and not want("off", basestation=True, speed=100.0)
    monkeypatch.setattr(options.os, "sched_getaffinity", lambda pid: {0, 1})
    assert not want("auto", basestation=True, speed=100.0)  # 2 cores shared with the team: measured worse


def test_a_bad_stage_workers_choice_is_one_line_and_exit_2():
    import subprocess
    import sys
    from pathlib import Path

    out = subprocess.run([str(Path(sys.executable).parent / "autopower"), "basestation", "--stage-workers", "maybe"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "--stage-workers" in out.stderr and "'maybe' is not one of 'off', 'on', 'auto'" in out.stderr


def test_a_prestarted_zygote_imports_while_the_node_goes_on():
    """A node with stage workers starts its worker factory at once and does not wait for it:
    seen in a live test, the first stage a robot took in a subgroup commit waited on its loop
    for the factory's start, and the loop stopped for 4.9 s (load ~8) while the base station
    took the team over without that robot."""
    from autopower.node.workers import Zygote

    zygote = Zygote()
    started = time.monotonic()
    zygote.prestart()
    try:
        assert time.monotonic() - started < 0.5  # a spawn, not its imports
        assert zygote._proc is not None and not zygote._ready
        time.sleep(3.0)  # its imports happen meanwhile (0.6 s at load 5)
        assert zygote._proc.poll() is None, "the factory died (it dies with the thread that started it)"
        forked = time.monotonic()
        sock, pid = zygote.fork()
        assert zygote._ready and time.monotonic() - forked < 1.0  # a fork, not a start
        sock.close()
        os.kill(pid, 9)
    finally:
        zygote.close()
