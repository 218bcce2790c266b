"""Each robot hears the part of the base station's status it acts on: its own chains' stages and
acknowledgements, whom the base station sees in full; the rest of a fleet's entries stay home."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

from autopower.basestation.peer_view import PeerViews
from autopower.protocol import Keys, NodeStatus, PeerStatus, decode, encode
from autopower.simulation.synthetic import paper_fleet

ROBOTS = 40


def base_status(robots: int) -> NodeStatus:
    blobs = [f"Blob-{i}" for i in range(1, robots + 1)]
    return NodeStatus(node="laptop", t_virtual=1.0, t_unix=1.0, plan_epoch=3, initial_j=None, battery_j=None,
                      energy_j={}, power_w={}, cpu_utilisation=0.0, hosted={b: "running" for b in blobs},
                      sources={}, sinks={}, links={f"r{i}": True for i in range(1, robots + 1)}, runs={},
                      compute_ms={}, queue_depth=0, errors={}, counters={}, depleted=False,
                      generations={b: 7 for b in blobs}, acks_wanted=("Blob-2", "Blob-3", "Map>Join"))


def test_a_robot_hears_its_own_chains_and_whom_the_base_station_sees():
    _, fleet = paper_fleet(ROBOTS)
    views = PeerViews(fleet, Keys("team"))
    status = base_status(ROBOTS)
    # r2 sources Loc-2 and Blob-2; the plan moves Loc-3 to it; it still runs Blob-5 from before
    chains = views.chains_of("r2", ({"Loc-3": "r2", "Blob-4": "laptop"}, {}), ("Blob-5",))
    assert chains == {"Loc-2", "Blob-2", "Loc-3", "Blob-5"}
    view = views.view(status, chains)
    assert view.hosted == {"Blob-2": "running", "Blob-5": "running"}  # Blob-5 here is newer: r2's stops
    assert view.generations == {"Blob-2": 7, "Blob-5": 7}
    assert view.acks_wanted == ("Blob-2", "Map>Join")  # a flow names no chain: kept
    # it sees every robot: the view names none of them, and reads as the status says
    assert view.links == {} and view.unseen == () and view.plan_epoch == 3 and view.node == "laptop"
    team = fleet.node_names()
    assert view.sees(team) == set(status.links)
    # what a robot hears does not grow with the fleet
    whole = dataclasses.replace(view, hosted=status.hosted, generations=status.generations, links=status.links,
                                unseen=None)
    assert len(encode(view)) < len(encode(whole)) / 4


def test_whom_the_base_station_sees_goes_in_the_shorter_form_and_reads_the_same():
    _, fleet = paper_fleet(ROBOTS)
    views, team = PeerViews(fleet, Keys("team")), fleet.node_names()
    for seen in (set(), {"r1"}, {f"r{i}" for i in range(1, 21)}, {f"r{i}" for i in range(2, ROBOTS + 1)}):
        status = dataclasses.replace(base_status(ROBOTS), links={f"r{i}": f"r{i}" in seen
                                                                 for i in range(1, ROBOTS + 1)})
        view = decode(encode(views.view(status, set())), PeerStatus)
        assert view.sees(team) == seen
        assert (view.unseen is not None) == (len(seen) > ROBOTS / 2)
        assert len(view.links) + len(view.unseen or ()) <= ROBOTS / 2


def test_a_robot_the_plan_does_not_name_still_hears_its_own_chains():
    _, fleet = paper_fleet(4)
    views = PeerViews(fleet, Keys("team"))
    assert views.chains_of("r4", ({}, {}), ()) == {"Loc-4", "Blob-4"}
    assert views.chains_of("nobody", ({}, {}), ("no-such-stage",)) == set()


def test_each_robot_in_reach_gets_its_view_on_its_own_key_and_before_the_mission_that_no_plan_runs():
    _, fleet = paper_fleet(3)
    keys = Keys("team")
    views = PeerViews(fleet, keys)
    r2_reported = SimpleNamespace(hosted={"Blob-3": "running"})
    co = SimpleNamespace(robots=["r1", "r2", "r3"], alive_nodes=lambda: {"laptop", "r1", "r2"},
                         statuses={"r2": r2_reported}, placing=SimpleNamespace(placement={"Loc-1": "r1"}, target={}),
                         takeover=SimpleNamespace(incarnation=0),
                         plans=SimpleNamespace(epoch=3, delivery=SimpleNamespace(sent={"r1": (0, 2), "r2": (0, 3)})))
    status = base_status(3)
    sent = list(views.addressed(co, status, 5.0, 2.0))
    assert [(robot, key) for robot, key, _ in sent] == [("r1", keys.addressed("r1", "laptop")),
                                                        ("r2", keys.addressed("r2", "laptop"))]  # r3 is gone
    r2 = decode(sent[1][2], PeerStatus)
    assert set(r2.hosted) == {"Blob-2", "Blob-3"} and r2.plan_epoch == 3
    # r1 was not sent plan 3 (it changes nothing r1 acts on, `PlanDelivery`): plan 2 is the newest for it
    assert decode(sent[0][2], PeerStatus).plan_epoch == 2
    before = [decode(payload, PeerStatus) for _, _, payload in views.addressed(co, None, 5.0, 2.0)]
    assert [(v.plan_epoch, v.hosted, v.t_unix, sorted(v.sees(fleet.node_names()))) for v in before] == \
        [(-1, {}, 5.0, ["r1", "r2"])] * 2
    assert before[0].unseen == ("r3",)  # the one out of sight, shorter than the two in it
    # the robots whose whole status the base station missed are asked for one, in their view alone
    asked = {robot: decode(payload, PeerStatus).send_whole
             for robot, _, payload in views.addressed(co, status, 5.0, 2.0, send_whole={"r2", "r3"})}
    assert asked == {"r1": False, "r2": True}
    assert not decode(sent[1][2], PeerStatus).send_whole
