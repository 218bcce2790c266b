"""`paper_fleet` (autopower.simulation.synthetic): the paper's mission on N robots, as a scenario file
the project's own loader accepts, and `autopower scenarios` (bare: the built-in list; `fleet`)."""

import json
from importlib import resources

import pytest
from click.testing import CliRunner

from autopower.cli.main import cli
from autopower.errors import ScenarioError
from autopower.model.loading import builtin_scenarios, load_scenario, load_toml, parse_scenario
from autopower.model.network import build_network
from autopower.simulation.synthetic import dumps_toml, paper_fleet, ring_links

PAPER = load_scenario("paper-fig7")


@pytest.mark.parametrize("n", [1, 3, 30, 100])
def test_the_text_loads_and_is_the_papers_mission_on_n_robots(n):
    text, scenario = paper_fleet(n)
    again = parse_scenario(text, "<again>")  # the text alone loads to the same team
    assert (again.robots, again.chains, again.network_spec) == (scenario.robots, scenario.chains,
                                                                scenario.network_spec)
    assert [r.name for r in scenario.robots] == [f"r{i}" for i in range(1, n + 1)]
    camera_robot = PAPER.robot("r2")
    for robot in scenario.robots:
        assert (robot.platform, robot.energy_j, robot.sensors) == (camera_robot.platform, camera_robot.energy_j,
                                                                   frozenset({"laser", "odometry", "camera"}))
    assert scenario.platforms == PAPER.platforms and scenario.radios == PAPER.radios
    assert {n: c.latency_s for n, c in scenario.components.items()} == {n: c.latency_s
                                                                        for n, c in PAPER.components.items()}
    assert (scenario.accounting, scenario.lifetime_rounding_s) == (PAPER.accounting, PAPER.lifetime_rounding_s)
    assert scenario.migration == PAPER.migration
    assert (scenario.basestation, scenario.basestation_platform) == (PAPER.basestation, PAPER.basestation_platform)
    assert scenario.network_spec == PAPER.network_spec  # fully connected, relay r1, the paper's media
    loc, blob = PAPER.chain("Loc-1"), PAPER.chain("Blob-2")
    assert len(scenario.chains) == 2 * n and len(scenario.stage_names()) == 2 * n
    for i in range(1, n + 1):
        for mine, theirs in ((scenario.chain(f"Loc-{i}"), loc), (scenario.chain(f"Blob-{i}"), blob)):
            assert mine.source == f"r{i}"
            assert (mine.sink == mine.source) == (theirs.sink == theirs.source)
            assert (mine.period_s, mine.message_bytes, mine.requires) == (theirs.period_s, theirs.message_bytes,
                                                                          theirs.requires)
            assert [s.component for s in mine.stages] == [s.component for s in theirs.stages]
    assert scenario.chain("Blob-1").period_s == 0.25  # 4 Hz


def test_k_cameras_give_k_blob_chains_on_the_robots_with_one():
    _, scenario = paper_fleet(10, 4, seed=3)
    blobs = [c for c in scenario.chains if c.name.startswith("Blob-")]
    with_camera = {r.name for r in scenario.robots if "camera" in r.sensors}
    assert len(blobs) == 4 and {c.source for c in blobs} == with_camera
    assert all(r.sensors >= {"laser", "odometry"} for r in scenario.robots)
    assert len([c for c in scenario.chains if c.name.startswith("Loc-")]) == 10
    _, none = paper_fleet(5, 0)
    assert "Blob" not in none.components and [c.name for c in none.chains] == [f"Loc-{i}" for i in range(1, 6)]


def test_the_seed_picks_the_cameras_and_nothing_else_varies():
    a, b = paper_fleet(20, 5, seed=7)[0], paper_fleet(20, 5, seed=7)[0]
    assert a == b
    others = {paper_fleet(20, 5, seed=s)[0] for s in range(8)}
    assert len(others) > 1  # another seed, other robots with the cameras
    assert paper_fleet(6, seed=1)[0].replace("--seed 1", "--seed 2") == paper_fleet(6, seed=2)[0]  # K = N


def test_relay_topology_and_media():
    _, relay = paper_fleet(6, topology="relay")
    assert relay.network_spec.topology == "relay" and relay.network_spec.relay == "r1"
    network = build_network(relay)
    uplinks = [{link.a, link.b} for link in network.links if link.touches("laptop")]
    assert network.topology == "relay" and uplinks == [{"r1", "laptop"}]
    _, one = paper_fleet(1, topology="relay")  # the relay alone
    assert one.network_spec.relay == "r1"
    text, wifi = paper_fleet(4, media=["802.11a"])
    assert wifi.network_spec.laptop_robot_media == wifi.network_spec.robot_robot_media == ("802.11a",)
    assert set(wifi.radios) == {"802.11a"} and "gsm" not in text
    _, two = paper_fleet(4, media=["bluetooth", "gsm", "bluetooth"])
    assert two.network_spec.robot_robot_media == ("bluetooth", "gsm")  # in order, once each


@pytest.mark.parametrize("args,message", [
    ((0,), "N must be >= 1"),
    ((3, 4), "--cameras must be between 0 and the number of robots (3)"),
    ((3, -1), "--cameras must be between 0"),
])
def test_bad_sizes_are_one_line_errors(args, message):
    with pytest.raises(ScenarioError) as info:
        paper_fleet(*args)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_an_unknown_medium_or_topology_is_refused():
    with pytest.raises(ScenarioError, match="unknown medium 'wifi': one of 802.11a, bluetooth, gsm"):
        paper_fleet(2, media=["802.11a", "wifi"])
    with pytest.raises(ScenarioError, match="unknown topology 'explicit'"):
        paper_fleet(2, topology="explicit")
    with pytest.raises(ScenarioError, match="--neighbours must be at least 1"):
        paper_fleet(4, topology="neighbours", neighbours=0)


@pytest.mark.parametrize("n,k", [(30, 1), (30, 2), (50, 3)])
def test_neighbours_link_each_robot_to_the_base_station_and_its_ring_neighbours_only(n, k):
    text, scenario = paper_fleet(n, topology="neighbours", neighbours=k)
    again = parse_scenario(text, "<again>")
    assert again.network_spec == scenario.network_spec
    network = build_network(scenario)
    assert len(network.links) == n + n * k  # a robot's links do not grow with the team
    for i in range(1, n + 1):
        peers = {l.b if l.a == f"r{i}" else l.a for l in network.links if l.touches(f"r{i}")}
        ring = {f"r{(i - 1 + d) % n + 1}" for d in range(-k, k + 1) if d}
        assert peers == ring | {"laptop"}, (i, peers)
    groups = {(l.a == "laptop" or l.b == "laptop"): l.medium for l in network.links}
    assert groups == {True: "802.11a", False: "802.11a"}  # the paper's first candidates per group


def test_a_small_ring_is_fully_connected_and_a_lone_robot_has_no_ring_link():
    assert ring_links(4, 2) == [(1, 2), (1, 3), (1, 4), (2, 3), (2, 4), (3, 4)]
    assert ring_links(2, 1) == [(1, 2)] and ring_links(1, 3) == []
    _, one = paper_fleet(1, topology="neighbours")
    assert [(l.a, l.b) for l in build_network(one).links] == [("r1", "laptop")]


def test_dumps_toml_round_trips_what_a_scenario_holds():
    data = {"scenario": {"name": 'quote " and \\ and é', "on": True, "n": 3, "x": 3.6e-05},
            "radios": {"802.11a": {"kbps": 54000}, "gsm": {"kbps": 116}},
            "components": {"C": {"latency_s": {"sitsang": 0.1, "laptop": 0.01}, "variants": {}}},
            "robots": [{"name": "r1", "sensors": ["laser"]}, {"name": "r2", "sensors": []}]}
    assert load_toml(dumps_toml(data), "<t>") == data
    paper = load_toml((resources.files("autopower.scenarios") / "paper-fig7.toml").read_text(), "<paper>")
    assert load_toml(dumps_toml(paper), "<paper again>") == paper
    with pytest.raises(ValueError, match="finite"):
        dumps_toml({"t": {"x": float("nan")}})


def test_bare_scenarios_still_lists_the_built_ins():
    out = CliRunner().invoke(cli, ["scenarios"])
    assert out.exit_code == 0, out.output
    lines = out.output.splitlines()
    assert [line.split(":")[0] for line in lines] == builtin_scenarios()
    assert lines[0] == f"paper-fig7: {PAPER.description}"


def test_fleet_without_out_prints_the_toml_and_nothing_else(tmp_path):
    out = CliRunner().invoke(cli, ["scenarios", "fleet", "3", "--cameras", "1", "--seed", "4"])
    assert out.exit_code == 0, out.output
    assert out.stdout == paper_fleet(3, 1, seed=4)[0]
    path = tmp_path / "f.toml"
    out = CliRunner().invoke(cli, ["scenarios", "fleet", "3", "--topology", "relay", "--out", str(path)])
    assert out.exit_code == 0, out.output
    assert path.read_text() == paper_fleet(3, topology="relay")[0]
    assert "fleet-3 — 3 robots (3 with a camera), 6 chains, 6 stages, relay" in out.output
    out = CliRunner().invoke(cli, ["scenarios", "fleet", "12", "--topology", "neighbours", "--neighbours", "2",
                                   "--out", str(path), "--json"])
    assert out.exit_code == 0, out.output
    summary = json.loads(out.stdout)
    assert (summary["topology"], summary["links"]) == ("explicit", 12 + 24)
    assert summary["media"] == {"laptop-robot": ["802.11a", "gsm"], "robot-robot": ["802.11a", "bluetooth"]}
    assert path.read_text() == paper_fleet(12, topology="neighbours", neighbours=2)[0]
