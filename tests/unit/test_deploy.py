"""Fleet files and node directories (no network): what `autopower deploy init` is built from."""

from __future__ import annotations

import pytest

from autopower.deploy.bundle import load_bundle, write_bundle
from autopower.deploy.fleet import load_fleet, node_settings
from autopower.deploy.pki import TeamCA, common_name
from autopower.errors import AutoPowerError
from autopower.model.loading import load_scenario
from autopower.runtime.bus import TlsFiles


def fleet_file(tmp_path, body: str):
    path = tmp_path / "fleet.toml"
    path.write_text(body)
    return path


FLEET = 'team = "lab"\n' + "".join(f'[nodes.{n}]\naddress = "10.0.0.{i}"\n'
                                   for i, n in enumerate(["laptop", "r1", "r2", "r3"], 1))


@pytest.mark.parametrize("body,needle", [
    ('team = "a/b"\n[nodes.r1]\naddress = "x"\n', "team"),
    ('team = "lab"\n', "no [nodes.NAME] tables"),
    ('team = "lab"\n[nodes.r1]\naddress = "x"\nport = 0\n', "nodes.r1.port = 0"),
    ('team = "lab"\n[nodes.r1]\naddress = "x"\nadress = "y"\n', "unknown field(s) adress"),
    ('team = "lab"\n[nodes.operator]\naddress = "x"\n', "operator CLI's identity"),
    ('team = "lab"\nlease_ms = 5\n[nodes.r1]\naddress = "x"\n', "lease_ms = 5"),
    ("team = \n", "not valid TOML"),
])
def test_bad_fleet_files_say_where_and_what(tmp_path, body, needle):
    with pytest.raises(AutoPowerError, match="fleet.toml") as info:
        load_fleet(fleet_file(tmp_path, body))
    assert needle in str(info.value)


def test_the_relay_topology_connects_only_linked_pairs(tmp_path):
    fleet = load_fleet(fleet_file(tmp_path, FLEET))
    scenario = load_scenario("paper-fig7")
    tls = TlsFiles(ca="ca.pem", cert="x.pem", key="x.key")
    relay = {n: node_settings(fleet, scenario, n, tls, topology="relay").connect for n in scenario.node_names()}
    full = {n: node_settings(fleet, scenario, n, tls).connect for n in scenario.node_names()}
    assert sum(map(len, full.values())) == 6
    assert sum(map(len, relay.values())) < 6  # unlinked pairs get no connection: the agents relay
    assert all(ep.startswith("tls/10.0.0.") and ep.endswith(":7447") for eps in full.values() for ep in eps)


def test_node_directory_round_trip_and_a_foreign_ca(tmp_path):
    written = write_bundle(tmp_path / "out", "paper-fig7", load_fleet(fleet_file(tmp_path, FLEET)))
    bundle = load_bundle(tmp_path / "out", "r2")
    assert bundle.node == "r2" and bundle.role == "robot" and bundle.team == "lab"
    assert bundle.zenoh.tls.key == str((written["r2"] / "r2.key").resolve())
    assert common_name(written["r2"] / "r2.pem") == "r2"
    with pytest.raises(AutoPowerError, match="not 'r1'"):
        load_bundle(written["r2"], "r1")
    with pytest.raises(AutoPowerError, match="node.json is missing"):
        load_bundle(tmp_path, "r2")
    with pytest.raises(AutoPowerError, match="no team CA"):
        TeamCA.load(tmp_path / "nowhere")
