"""A component that misbehaves stops its own stage, nothing else.

Each case runs the whole team in one thread (`SimTeam`: coordinator + a NodeRuntime per node) with
the fake counting components, except one stage whose component raises, returns something that is
not bytes, writes more than its chain declares, hangs, or cannot take its own state back. The
node hosting it must keep running every other stage (their outputs exactly once), report the
stage as failed with the exception text, and tell the base station, which stops that chain.
"""

from __future__ import annotations

import re
import threading
import time

import msgpack
import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node import guard
from autopower.node.ports import SinkListener
from autopower.node.stages import Lifecycle
from autopower.protocol import MigrateCommand
from tests.unit.sim_team import FakeComponent, FakeSource, SimTeam

FC = {"laptop-robot": "802.11a", "robot-robot": "802.11a"}
BAD = "Blob-2"  # the stage whose component misbehaves (pinned to r2, which also runs Loc-2)
RELEASE = threading.Event()  # lets hung components' threads end when the tests are done


class Raises(FakeComponent):
    def run(self, payload):
        seq = msgpack.unpackb(payload)[1]
        if seq == 3:
            raise ValueError("no blobs in a black frame")
        return super().run(payload)


class NotBytes(FakeComponent):
    def run(self, payload):
        out = super().run(payload)
        return out if self.count < 3 else out.decode("latin-1")


class Oversize(FakeComponent):
    def run(self, payload):
        out = super().run(payload)
        return out if self.count < 3 else out + bytes(1000)  # Blob-2 declares 200 B


class Hangs(FakeComponent):
    def run(self, payload):
        if self.count >= 2:
            RELEASE.wait(60)
        return super().run(payload)


class StateDoesNotImport(FakeComponent):
    def import_state(self, state):
        raise ValueError("state format 2 not understood")


class ExportFails(FakeComponent):
    def export_state(self):
        raise RuntimeError("camera handle cannot be serialised")


def team_with(bad_cls, *, speed: float = 1.0, pins=None, node_kwargs=None) -> SimTeam:
    """``node_kwargs``: node -> its runtime's factories over this team's (`SimTeam`)."""
    def make_component(component_type, robot, seed):
        cls = bad_cls if (component_type, robot) == ("Blob", "r2") else FakeComponent
        return cls(component_type, robot, seed)

    team = SimTeam(load_scenario("paper-fig7"),
                   config=CoordinatorConfig(speed=speed, media=FC, auto_replan=False,
                                            pins=pins or {BAD: "r2", "Loc-2": "r2"}),
                   fake=True, speed=speed,
                   node_kwargs={node: {"make_component": make_component, **(node_kwargs or {}).get(node, {})}
                                for node in load_scenario("paper-fig7").node_names()})
    return team


@pytest.fixture(autouse=True)
def _release_hung_threads():
    RELEASE.clear()
    yield
    RELEASE.set()


def outputs_of(team: SimTeam) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: out.setdefault(chain, []).append(seq)))
    return out


def assert_others_unharmed(team: SimTeam, outputs: dict[str, list[int]]) -> None:
    for chain in team.scenario.chains:
        if chain.name == BAD:
            continue
        produced = team.nodes[chain.source].sources[chain.name].seq
        assert produced > 5
        assert sorted(outputs[chain.name]) == list(range(produced)), chain.name


@pytest.mark.parametrize("bad_cls, what, text", [
    (Raises, "raised", "ValueError: no blobs in a black frame"),
    (NotBytes, "not-bytes", "returned str, not bytes"),
    (Oversize, "oversize", "run(seq 2) returned 1003 B; the chain declares message_bytes 200"),
])
def test_a_failing_component_stops_its_stage_only(bad_cls, what, text):
    team = team_with(bad_cls)
    outputs = outputs_of(team)
    team.join()
    team.run_until(20.0)
    r2 = team.nodes["r2"]
    # the node says so, in every status, with the exception text
    status = r2.status(10.0)
    assert status.failed[BAD].startswith(f"{what}: ") and text in status.failed[BAD]
    assert r2.errors["stage-failed"] == 1
    # the base station heard, stopped that chain and re-planned the others
    co = team.coordinator
    assert BAD in co.operating.failed_stages and text in co.operating.failed_stages[BAD]
    assert "Blob-2" in co.operating.disabled and BAD not in co.placing.placement
    assert BAD not in r2.hosted  # released
    assert any("Blob-2 failed on r2" in note for note in co.events)
    # what ran before the failure reached the sink; nothing after it
    assert sorted(outputs.get(BAD, [])) == list(range(len(outputs.get(BAD, []))))
    assert len(outputs.get(BAD, [])) <= 3
    # r2 goes on: its Loc-2 and everyone else's chains, exactly once
    assert team.coordinator.placing.placement["Loc-2"] == "r2"
    assert_others_unharmed(team, outputs)


def test_a_hung_component_is_abandoned_after_the_stated_limit(monkeypatch):
    assert guard.hang_limit_s(period_s=0.25, speed=1.0) == guard.HANG_MIN_WALL_S  # 3 periods < 2 s
    assert guard.hang_limit_s(period_s=2.0, speed=1.0) == 6.0  # 3 periods of a slow chain
    monkeypatch.setattr(guard, "HANG_MIN_WALL_S", 0.2)  # the test's patience, not the product's
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.1)
    team = team_with(Hangs, speed=10.0)  # Blob-2: 0.25 s period at x10 -> 3 periods = 75 ms wall
    outputs = outputs_of(team)
    team.join()
    team.run_until(20.0)
    r2 = team.nodes["r2"]
    assert re.fullmatch(r"hung: run\(seq 2\): no result after [\d.]+ s \(blocked; limit 0\.2 s\)",
                        r2.status(10.0).failed[BAD])
    assert r2.guard.abandoned == 1
    assert "Blob-2" in team.coordinator.operating.disabled
    assert_others_unharmed(team, outputs)  # Loc-2 on the same node ran on a fresh worker


@pytest.mark.parametrize("bad_cls, what", [(StateDoesNotImport, "import-failed"), (ExportFails, "export-failed")])
def test_a_state_that_cannot_move_keeps_the_stage_where_it_runs(bad_cls, what):
    team = team_with(bad_cls, pins={BAD: "r2"})
    outputs = outputs_of(team)
    team.join()
    team.run_until(5.0)
    co = team.coordinator
    assert co.on_operator(MigrateCommand(stage=BAD, to_node="r3")).ok
    team.pump()
    team.run_until(20.0)
    # the migration was abandoned; the stage runs on where it was, with its state
    assert not co.placing.migrations and co.placing.aborted == 1
    assert co.placing.placement[BAD] == "r2" and co.operating.pins[BAD] == "r2"
    assert team.nodes["r2"].hosted[BAD].lifecycle is Lifecycle.RUNNING
    assert BAD not in team.nodes["r3"].hosted
    assert team.nodes["r2"].errors[what] == 1 and not team.nodes["r2"].hosting.failed
    assert "Blob-2" not in co.operating.disabled
    assert any("migration r2 -> r3 refused" in note and what in note for note in co.events)
    produced = team.nodes["r2"].sources[BAD].seq
    assert sorted(outputs[BAD]) == list(range(produced))  # exactly once, the count carried on (FakeComponent)
    assert_others_unharmed(team, outputs)


def test_a_state_that_imports_at_home_but_not_on_the_new_host_goes_on_there_without_it():
    """Different code on the new host (the check on the old one passed): it starts there without the
    state, from the seq where the old host stopped: no input lost or run twice."""
    r3_makes = lambda kind, robot, seed: (StateDoesNotImport if kind == "Blob" else  # noqa: E731
                                          FakeComponent)(kind, robot, seed)
    team = team_with(FakeComponent, pins={BAD: "r2"}, node_kwargs={"r3": {"make_component": r3_makes}})
    outputs: dict[str, list[tuple[int, bytes]]] = {}
    for rt in team.nodes.values():
        rt.listen(SinkListener(output=lambda chain, run, seq, data: outputs.setdefault(chain, []).append((seq, data))))
    team.join()
    team.run_until(5.0)
    co = team.coordinator
    assert co.on_operator(MigrateCommand(stage=BAD, to_node="r3")).ok
    team.pump()
    assert co.placing.placement[BAD] == "r3" and co.placing.migrations_done == 1 and not co.placing.aborted
    assert team.nodes["r3"].errors["import-failed"] == 1
    assert any("r3: import-failed: state from r2 did not import, started without it: import_state: ValueError"
               in note for note in co.events)
    team.run_until(20.0)
    produced = team.nodes["r2"].sources[BAD].seq
    assert sorted(seq for seq, _ in outputs[BAD]) == list(range(produced))  # exactly once
    counts = [msgpack.unpackb(data)[1] for _, data in sorted(outputs[BAD])]
    restart = counts.index(1, 1)  # the fresh instance counts from 1 again: nothing else changed
    assert counts == list(range(1, restart + 1)) + list(range(1, produced - restart + 1))
    assert "Blob-2" not in co.operating.disabled


def test_a_hung_source_stops_its_chain_not_its_robot(monkeypatch):
    monkeypatch.setattr(guard, "HANG_MIN_WALL_S", 0.2)
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.1)

    class HungCamera(FakeSource):
        def produce(self, seq):
            if seq == 4:
                RELEASE.wait(60)
            return super().produce(seq)

    r2_sources = lambda kind, robot, seed: (HungCamera if kind == "Blob" else FakeSource)(  # noqa: E731
        kind, robot, seed)
    team = team_with(FakeComponent, speed=10.0, node_kwargs={"r2": {"make_source": r2_sources}})
    outputs = outputs_of(team)
    team.join()
    team.run_until(20.0)
    r2, co = team.nodes["r2"], team.coordinator
    [(what, why)] = r2.status(10.0).failed.items()
    assert what == "Blob-2 source"
    assert re.fullmatch(r"hung: produce\(seq 4\): no result after [\d.]+ s \(blocked; limit 0\.2 s\)", why)
    assert "Blob-2" not in r2.sources and r2.status(10.0).sources["Blob-2"].produced == 4
    assert "Blob-2" in co.operating.disabled and "source-hung" in co.operating.failed_stages[BAD]
    assert sorted(outputs[BAD]) == [0, 1, 2, 3]
    assert_others_unharmed(team, outputs)  # r2's Loc-2 source and stage went on


# ---- the hang verdict itself ----------------------------------------------------------------------------


def _spin(seconds: float) -> str:
    end = time.monotonic() + seconds
    while time.monotonic() < end and not RELEASE.is_set():
        pass
    return "done"


def test_a_blocked_call_is_hung_soon_after_its_limit(monkeypatch):
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.1)
    calls = guard.GuardedCalls()
    started = time.monotonic()
    with pytest.raises(guard.ComponentHung, match=r"\(blocked; limit 0\.2 s\)"):
        calls.call(RELEASE.wait, 60, timeout_s=0.2)
    # the limit and a probe at least; a blocked call never waits for the spin limit (10 x 0.2 s)
    assert 0.3 <= time.monotonic() - started < 2.0
    assert calls.call(lambda: "next", timeout_s=0.2) == "next"  # on a new worker
    assert calls.abandoned == 1


def test_a_slow_call_that_computes_is_not_hung(monkeypatch):
    # what a saturated machine looks like: past the limit, still using CPU -> waited for
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.25)
    calls = guard.GuardedCalls()
    assert calls.call(_spin, 0.6, timeout_s=0.2) == "done"
    assert calls.abandoned == 0


def test_a_spinning_call_is_hung_after_the_spin_limit(monkeypatch):
    monkeypatch.setattr(guard, "BLOCKED_PROBE_S", 0.1)
    monkeypatch.setattr(guard, "SPIN_FACTOR", 4)
    calls = guard.GuardedCalls()
    started = time.monotonic()
    with pytest.raises(guard.ComponentHung, match=r"\(still running; limit 0\.2 s\)"):
        calls.call(_spin, 60, timeout_s=0.2)
    assert 0.8 <= time.monotonic() - started < 1.5


def test_builtin_components_run_on_the_loop_thread_plugins_on_the_worker():
    class Plugin:
        def run(self, payload):
            return threading.get_ident()

    class Shipped(Plugin):
        pass

    Shipped.__module__ = "autopower.chains.blobfinder"  # as the built-in components are
    calls = guard.GuardedCalls()
    assert calls.call(Shipped().run, b"", timeout_s=1.0) == threading.get_ident()
    assert calls.call(Plugin().run, b"", timeout_s=1.0) != threading.get_ident()
