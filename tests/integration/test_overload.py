"""An overloaded node stays a member of the team: its loop is held up, its peers still hear it.

A real team (base station + two agents, mutual TLS, the worked plug-in example) runs with
Motion-1's detector on the base station, and that detector computes for 1.5 s on each of four
frames (`faulty_components.SlowAtHundred`): a bounded overload of the base station's one event
loop, 6 s during which it builds no status. Its peers' silence detectors wait 1 s for a status;
before the fix, every robot declared the base station out of sight ("no status for 1.x s; its
token is still here"), the base station saw its links reported down and replanned, and the team
treated an overloaded base station as a cut network (measured in the whole-mission benchmark at
x55, where bursts of inputs released at once held the loop for 0.2–0.6 s per event). Now the
base station's bus puts its last status again while the loop is late (`Bus.repeat_until_next`).
Asserted: statuses keep arriving, no peer goes out of sight, no link down, no replan, no subgroup
round, the repeats are counted, and afterwards every output arrives exactly once and equal to an
offline run. Bounded: four slow frames, a few seconds.
"""

from __future__ import annotations

import threading
import time

from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec, endpoint
from autopower.protocol import Keys, NodeStatus, StatusDelta, decode
from autopower.protocol.statuses import StatusAssembler
from autopower.runtime.bus import ZenohBus, ZenohSettings
from autopower.runtime.cadence import silence_limit_s
from tests.integration.runtime_helpers import reference_digest, settled, sinks_of, wait_for
from tests.integration.test_plugin_components import plugin_path, with_component  # noqa: F401  (a fixture)


def slow_scenario(tmp_path):
    return with_component(tmp_path, "Motion-1", "Slow", "tests.integration.faulty_components:SlowAtHundred")


def test_a_base_station_held_up_by_a_slow_stage_stays_in_the_team(plugin_path, tmp_path):  # noqa: F811
    from tests.integration.faulty_components import SLOW_FRAMES, SLOW_S  # needs the example on the path

    path = slow_scenario(tmp_path)
    scenario = build_scenario(str(path))
    spec = TeamSpec(scenario=str(path), speed=10.0, auto_replan=False, pins=("Motion-1=laptop",),
                    log_dir=tmp_path / "logs")
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        keys = Keys(team.team)
        base = scenario.basestation
        arrivals: list[tuple[float, float]] = []  # when each status came, the period it announced
        identity = team.identities.files(base) if team.identities else None
        settings = ZenohSettings(connect=(endpoint(team.ports[base], scheme=team.scheme),), tls=identity)
        watching = threading.Event()
        # listening from before the team settles: a whole status comes meanwhile (`protocol.statuses`),
        # so the period each change after it announces is known
        with ZenohBus(settings) as observer:
            statuses = StatusAssembler()

            def arrived(_key: str, payload: bytes) -> None:
                status = statuses.whole(decode(payload, (NodeStatus, StatusDelta)))
                if not watching.is_set():
                    return
                # a change from a whole status not held: it came; the longest period it may have announced
                announced = status.next_status_s if status is not None else spec.heartbeat_s
                arrivals.append((time.monotonic(), announced))

            observer.subscribe(keys.status(base), arrived)
            snap = wait_for(team, settled, 30, "the team to settle")
            assert snap["placement"]["Motion-1"] == "laptop"
            assert sinks_of(snap).get("Motion-1", {}).get("contiguous", 0) < SLOW_FRAMES.start, \
                "the slow frames came before the team settled: nothing left to observe"
            epoch, events_before = snap["epoch"], len(snap.get("events") or [])
            watching.set()
            watched_from = time.monotonic()
            wait_for(team, lambda s: sinks_of(s).get("Motion-1", {}).get("contiguous", 0) >= SLOW_FRAMES.stop + 20,
                     30 + len(SLOW_FRAMES) * SLOW_S * 3, "Motion-1 to get past its slow frames")
            watched_s = time.monotonic() - watched_from
        later = wait_for(team, lambda s: all(v["contiguous"] >= SLOW_FRAMES.stop + 40 for v in sinks_of(s).values()),
                         30, "both chains to go on")
        team.check_children()
        logs = {name: child.log_path.read_text() for name, child in team.children.items()}
    # the loop was held up (else this tested nothing), and its status went out all the same
    assert later["basestation"]["counters"].get("status-repeats", 0) >= 1, later["basestation"]["counters"]
    # the frames that waited in its queue meanwhile were not taken for lost: its statuses said how long
    # its queue waited, so the robots resent none of them (before: each one waiting over 1 s, decoded
    # by the base station only to be dropped as redundant); nothing was lost on the way, so none at all
    resent = {r: (info["status"].get("counters") or {}).get("resent-frames", 0) for r, info in later["robots"].items()}
    assert not any(resent.values()), resent
    assert later["basestation"]["counters"].get("redundant-input", 0) == 0, later["basestation"]["counters"]
    # each status came before the robots' silence detectors stopped waiting for it (what the one
    # before it announced: 2 periods, at rest 2 rest periods, never less than the lease)
    # (a status each heartbeat at least, the counts moving with nothing else new: enough to judge)
    assert len(arrivals) >= max(4, watched_s / spec.heartbeat_s - 1), (len(arrivals), watched_s)
    for (t0, announced), (t1, _) in zip(arrivals, arrivals[1:], strict=False):
        limit = silence_limit_s(2.0, spec.status_period_s, announced, spec.lease_ms / 1000)
        assert t1 - t0 < limit, f"no status from the base station for {t1 - t0:.2f} s (its peers wait {limit:.2f} s)"
    for name, text in logs.items():
        assert "out of sight" not in text, f"{name} lost sight of a peer\n{text[-3000:]}"
        assert "subgroup round" not in text, f"{name} took part in a subgroup round\n{text[-3000:]}"
        assert "Closing transport" not in text, f"{name}: a Zenoh transport closed\n{text[-3000:]}"
    new_events = (later.get("events") or [])[events_before:]
    assert later["epoch"] == epoch, new_events
    assert not [e for e in new_events if " down" in e or " left" in e or "lost" in e], new_events
    for chain, stats in sinks_of(later).items():
        assert stats["duplicates_total"] == 0, chain
        assert stats["digest"] == reference_digest(scenario, chain, stats["contiguous"]), chain


def test_a_status_is_put_again_only_while_the_next_is_late_and_not_for_ever(monkeypatch):
    """`ZenohBus.repeat_until_next` between two real sessions: copies while late, none while on time,
    none after `REPEAT_FOR_S`, none after close."""
    from autopower.launch.localhost import free_ports
    from autopower.runtime import bus as bus_module

    monkeypatch.setattr(bus_module, "REPEAT_FOR_S", 1.0)
    at = endpoint(free_ports(1)[0])
    got: list[tuple[float, bytes]] = []
    with ZenohBus(ZenohSettings(listen=(at,))) as receiver, ZenohBus(ZenohSettings(connect=(at,))) as sender:
        receiver.subscribe("st/x", lambda _k, p: got.append((time.monotonic(), p)))
        deadline = time.monotonic() + 20
        while not got:  # until the link is up
            assert time.monotonic() < deadline, "the two sessions never connected"
            sender.publish("st/x", b"hello", reliable=False)
            time.sleep(0.05)
        # on time: a new one every 0.1 s, each due within 0.3 s: no copy
        got.clear()
        for _ in range(10):
            sender.publish("st/x", b"on-time", reliable=False)
            sender.repeat_until_next("st/x", b"on-time", 0.3, 0.1)
            time.sleep(0.1)
        assert sender.repeated == 0
        # late: the loop is held up; copies after 0.3 s, then every 0.1 s, until REPEAT_FOR_S (1 s)
        sender.publish("st/x", b"late", reliable=False)
        sender.repeat_until_next("st/x", b"late", 0.3, 0.1)
        time.sleep(1.6)
        late = [t for t, p in got if p == b"late"]
        assert 5 <= len(late) - 1 <= 9, len(late)  # the original, then about 7 copies
        assert late[1] - late[0] > 0.25
        assert late[-1] - late[0] < 1.1  # none after REPEAT_FOR_S
        copies = sender.repeated
        sender.publish("st/x", b"last", reliable=False)
        sender.repeat_until_next("st/x", b"last", 0.3, 0.1)
    time.sleep(0.5)  # closed before it was due: nothing more
    assert [p for _, p in got].count(b"last") == 1
    assert copies == len(late) - 1
