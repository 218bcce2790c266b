"""Fleet files and node directories (no network): what `autopower deploy init` is built from."""

from __future__ import annotations

import json
import re
import stat

import pytest

from autopower.deploy.bundle import load_bundle, write_bundle
from autopower.deploy.fleet import Fleet, load_fleet, node_settings, operator_settings
from autopower.deploy.pki import TeamCA, common_name
from autopower.errors import AutoPowerError
from autopower.launch.localhost import TeamSpec, check_transport
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


# ---- the links' transport: TLS over TCP or Zenoh's QUIC link -----------------------------------------


@pytest.mark.parametrize("body,needle", [
    ('team = "lab"\ntransport = "udp"\n[nodes.r1]\naddress = "x"\n', "transport = 'udp'; expected one of 'tls', 'quic'"),
    ('team = "lab"\ntransport = "QUIC"\n[nodes.r1]\naddress = "x"\n', "transport = 'QUIC'"),
    ('team = "lab"\ntransport = 1\n[nodes.r1]\naddress = "x"\n', "transport = 1"),
    # a misspelt field would otherwise leave the team on TLS without a word
    ('team = "lab"\ntransprot = "quic"\n[nodes.r1]\naddress = "x"\n', "unknown field(s) transprot"),
])
def test_a_bad_transport_says_where_and_what(tmp_path, body, needle):
    with pytest.raises(AutoPowerError, match="fleet.toml") as info:
        load_fleet(fleet_file(tmp_path, body))
    assert needle in str(info.value)


def test_the_transport_defaults_to_tls_and_a_fleet_refuses_another(tmp_path):
    fleet = load_fleet(fleet_file(tmp_path, FLEET))
    assert fleet.transport == "tls"
    assert fleet.endpoint("r1", "laptop") == "tls/10.0.0.1:7447"
    with pytest.raises(AutoPowerError, match="transport 'tcp'"):
        Fleet(team="lab", nodes=fleet.nodes, transport="tcp")


def test_a_quic_fleet_links_its_nodes_over_quic_and_the_operator_over_tls(tmp_path):
    fleet = load_fleet(fleet_file(tmp_path, 'transport = "quic"\n' + FLEET))
    scenario = load_scenario("paper-fig7")
    tls = TlsFiles(ca="ca.pem", cert="x.pem", key="x.key")
    settings = {n: node_settings(fleet, scenario, n, tls) for n in scenario.node_names()}
    # every link between nodes is QUIC, each pair once (the node later in the scenario's order connects)
    assert {n: s.connect for n, s in settings.items()} == {
        "r1": (), "r2": ("quic/10.0.0.2:7447",), "r3": ("quic/10.0.0.2:7447", "quic/10.0.0.3:7447"),
        "laptop": ("quic/10.0.0.2:7447", "quic/10.0.0.3:7447", "quic/10.0.0.4:7447")}
    for robot in ("r1", "r2", "r3"):
        assert settings[robot].listen == (f"quic/{fleet.nodes[robot].address}:7447",)
    # the base station also takes the operator's TLS connection, on the same port number (TCP)
    assert settings["laptop"].listen == ("quic/10.0.0.1:7447", "tls/10.0.0.1:7447")
    assert operator_settings(fleet, scenario, tls).connect == ("tls/10.0.0.1:7447",)
    tls_fleet = load_fleet(fleet_file(tmp_path, FLEET))
    assert node_settings(tls_fleet, scenario, "laptop", tls).listen == ("tls/10.0.0.1:7447",)


def test_a_quic_node_directory_has_quic_endpoints_with_the_teams_tls_files(tmp_path):
    fleet = load_fleet(fleet_file(tmp_path, 'transport = "quic"\n' + FLEET))
    written = write_bundle(tmp_path / "out", "paper-fig7", fleet, install_dir="/etc/autopower")
    for node in ("laptop", "r2"):
        config = json.loads("\n".join(line for line in (written[node] / "zenoh.json5").read_text().splitlines()
                                      if not line.startswith("//")))
        assert config["listen"]["endpoints"][0].startswith("quic/"), config["listen"]
        assert all(ep.startswith("quic/") for ep in config["connect"]["endpoints"]), config["connect"]
        # Zenoh's QUIC link reads the TLS section: the team CA, the node's certificate both ways, mTLS
        assert config["transport"]["link"]["tls"] == {
            "root_ca_certificate": "/etc/autopower/ca.pem",
            "listen_certificate": f"/etc/autopower/{node}.pem", "listen_private_key": f"/etc/autopower/{node}.key",
            "connect_certificate": f"/etc/autopower/{node}.pem", "connect_private_key": f"/etc/autopower/{node}.key",
            "enable_mtls": True, "verify_name_on_connect": True}
        assert config["access_control"]["enabled"] and config["access_control"]["default_permission"] == "deny"
        assert stat.S_IMODE((written[node] / f"{node}.key").stat().st_mode) == 0o600
    assert json.loads((written["r3"] / "node.json").read_text())["zenoh"]["connect"] == [
        "quic/10.0.0.2:7447", "quic/10.0.0.3:7447"]
    bundle = load_bundle(tmp_path / "out", "laptop")
    assert bundle.zenoh.listen == ("quic/10.0.0.1:7447", "tls/10.0.0.1:7447")
    assert json.loads((written["operator"] / "node.json").read_text())["zenoh"]["connect"] == ["tls/10.0.0.1:7447"]


@pytest.mark.parametrize("changes,needle", [
    ({"transport": "udp"}, "transport 'udp'"),
    ({"transport": "quic", "secure": False}, "--insecure is plain tcp"),
    ({"transport": "quic", "proxied_links": True}, "link proxies forward TCP"),
])
def test_a_local_team_refuses_a_transport_it_cannot_run(changes, needle):
    with pytest.raises(AutoPowerError, match=re.escape(needle)):
        check_transport(TeamSpec(scenario="paper-fig7", **changes))
    check_transport(TeamSpec(scenario="paper-fig7", transport="quic"))  # secure, direct links: fine
