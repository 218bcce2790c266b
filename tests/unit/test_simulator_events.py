"""Events files are validated strictly (file, line, field); the shipped ones load; the CLI command."""

import json

import pytest
from click.testing import CliRunner

from autopower.cli.simulate import simulate as simulate_cmd
from autopower.errors import AutoPowerError, ScenarioError
from autopower.model.loading import load_scenario
from autopower.model.mission_events import EventsError, builtin_events, load_events, parse_events

FIG7 = load_scenario("paper-fig7")

LINK_CUT = '[[events]]\nat_s = 1\nkind = "link-cut"\na = "r1"\nb = "laptop"\n'


@pytest.mark.parametrize("text,message", [
    ("[simulaton]\nx = 1\n", "ev.toml:1: simulaton: unknown key; expected one of events, migration, simulation"),
    (LINK_CUT + 'robot = "r2"\n', "ev.toml:6: events[0].robot: unknown key; expected one of a, at_s, b, kind, note"),
    ('[[events]]\nat_s = 1\nkind = "meteor"\n', "ev.toml:3: events[0].kind: found 'meteor'; expected one of link-cut"),
    (LINK_CUT + '\n[[events]]\nat_s = -5\nkind = "link-heal"\na = "r1"\nb = "laptop"\n',
     "ev.toml:8: events[1].at_s: found -5; expected a number >= 0.0"),
    ('[[events]]\nat_s = 10\nkind = "link-heal"\na = "r1"\nb = "laptop"\n',
     "ev.toml:1: events[0]: link r1–laptop is not cut at 10 s; expected a link-cut before it"),
    (LINK_CUT + LINK_CUT, "ev.toml:6: events[1]: link r1–laptop is already cut at 1 s"),
    ('[[events]]\nat_s = 10\nkind = "robot-leave"\nrobot = "r7"\n',
     "ev.toml:4: events[0].robot: found 'r7'; expected one of r1, r2, r3"),
    ('[[events]]\nat_s = 10\nkind = "radio-fault"\nrobot = "r3"\nlaptop_robot = "wifi"\n',
     "ev.toml:5: events[0].laptop_robot: found 'wifi'; expected one of 802.11a, bluetooth, gsm"),
    ('[[events]]\nat_s = 10\nkind = "radio-fault"\nrobot = "r3"\n', "a radio fault that changes nothing"),
    ('[[events]]\nat_s = 10\nkind = "radio-repair"\nrobot = "r3"\n', "r3 has no radio fault at 10 s"),
    ("[migration]\nstate_bytes = { Loc = -1 }\n",
     "ev.toml:2: migration.state_bytes.Loc: found -1; expected a whole number of bytes >= 0"),
    ("[migration]\nstate_bytes = { Lok = 1 }\n", "migration.state_bytes.Lok: unknown key; expected one of Blob, Loc"),
    ("[migration]\ndowntime_s = -1\n", "migration.downtime_s: found -1; expected a number >= 0.0"),
    ('[[events]]\nat_s = 1\nkind = "chain-disable"\nchains = ["Blob-2"]\n'
     '[[events]]\nat_s = 2\nkind = "chain-disable"\nchains = ["Blob-2"]\n',
     "ev.toml:8: events[1].chains: Blob-2 is already disabled at 2 s; expected an enabled chain"),
    ('[[events]]\nat_s = 1\nkind = "chain-enable"\nchains = ["Blob-9"]\n', "events[0].chains: found 'Blob-9'"),
    ('[[events]]\nat_s = 1\nkind = "energy-offset"\nrobot = "r1"\ndelta_j = 0\n',
     "ev.toml:5: events[0].delta_j: found 0; expected a non-zero change in joules"),
    ('[[events]]\nat_s = 1\nkind = "robot-join"\nrobot = "r1"\n', "r1 is already in the team at 1 s"),
    ('[simulation]\ninitially_absent = ["r1", "r2", "r3"]\n', "every robot is absent"),
    ("[simulation]\nbattery_noise = 0.9\n", "simulation.battery_noise: found 0.9; expected a relative error < 0.5"),
    ('[[events]]\nkind = "robot-join"\nrobot = "r1"\n', "ev.toml:1: events[0]: missing required key 'at_s'"),
    ("[[events]\n", "ev.toml: not valid TOML"),
])
def test_bad_events_files_say_where_and_what(text, message):
    with pytest.raises(EventsError) as err:
        parse_events(text, FIG7, "ev.toml")
    assert message in str(err.value)
    assert isinstance(err.value, ScenarioError) and isinstance(err.value, AutoPowerError)


def test_a_cut_must_name_a_link_of_the_topology():
    text = '[[events]]\nat_s = 10\nkind = "link-cut"\na = "r2"\nb = "laptop"\n'
    parse_events(text, FIG7)  # fully connected: r2 talks to the laptop
    with pytest.raises(EventsError, match="no link r2–laptop on the relay topology; expected a link of the topology"):
        parse_events(text, FIG7, topology="relay")


def test_events_are_sorted_by_time_keeping_file_order_for_ties():
    text = """
[[events]]
at_s = 50
kind = "energy-offset"
robot = "r1"
delta_j = 10
[[events]]
at_s = 5
kind = "robot-leave"
robot = "r2"
[[events]]
at_s = 50
kind = "robot-join"
robot = "r2"
"""
    script = parse_events(text, FIG7)
    assert [e.kind for e in script.events] == ["robot-leave", "energy-offset", "robot-join"]
    assert script.events[0].describe() == "r2 left the team"


@pytest.mark.parametrize("name", ["paper-vc-fault", "cameras-off", "link-cuts"])
def test_shipped_events_files_load(name):
    assert name in builtin_events()
    script = load_events(name, FIG7, topology="relay" if name == "cameras-off" else None)
    assert script.events and script.description


def test_missing_events_file_is_a_clear_error(tmp_path):
    with pytest.raises(EventsError, match="no such events file"):
        load_events(tmp_path / "nope.toml", FIG7)
    with pytest.raises(EventsError, match="neither an events file nor a built-in one; built-in: cameras-off"):
        load_events("nope", FIG7)


# ---- the CLI command ---------------------------------------------------------------------------------


def test_simulate_command_json_compares_with_the_bound():
    res = CliRunner().invoke(simulate_cmd, ["paper-fig7", "--topology", "relay", "--policy", "all", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    policies = out["policies"]
    assert set(policies) == {"static", "reactive", "rebalance", "subgroup"}
    assert policies["rebalance"]["fraction_of_bound"] >= 0.98
    assert policies["static"]["fraction_of_bound"] == pytest.approx(0.9724, abs=1e-4)


def test_simulate_command_with_events_prints_the_decisions():
    res = CliRunner().invoke(simulate_cmd, ["paper-fig7", "--events", "paper-vc-fault", "--policy", "reactive"])
    assert res.exit_code == 0, res.output
    assert "1564.4%" in res.output  # the reason the old plan cannot go on (rich may wrap the line)
    assert "reactive" in res.output and "r3 ran dry" in res.output


@pytest.mark.parametrize("args,message", [
    (["paper-fig7", "--events", "nope"], "neither an events file nor a built-in one"),
    (["paper-fig7", "--policy", "all", "--record", "x.rrd"], "--record needs one --policy"),
    (["paper-fig7", "--record", "/nonexistent-dir/x.rrd"], "folder /nonexistent-dir does not exist"),
    (["nope-scenario"], "neither a scenario file nor a built-in scenario"),
])
def test_simulate_command_errors_are_autopower_errors(args, message):
    res = CliRunner().invoke(simulate_cmd, args)
    assert res.exit_code != 0
    assert isinstance(res.exception, AutoPowerError) and message in str(res.exception)
