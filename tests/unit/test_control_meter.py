"""The control plane's bytes (autopower.node.control_meter, autopower.runtime.link_traffic): what a
node's links carried beyond its chain packets, charged to the radio of each link as ``control``."""

from __future__ import annotations

import dataclasses
import socket

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.energy import airtime_s
from autopower.model.loading import load_scenario
from autopower.node.control_meter import ControlPlaneMeter
from autopower.runtime.link_traffic import (
    KEEP_UNSEEN_READINGS,
    LinkTraffic,
    SocketTotals,
    canonical,
    parse_endpoint,
    supported,
    tcp_connections,
)
from tests.unit.sim_team import SimTeam

SC = load_scenario("paper-fig7")
ZID_LAPTOP, ZID_R2 = "a1" * 16, "b2" * 16


# ---- link_traffic ------------------------------------------------------------------------------------


def test_endpoints_are_read_as_the_kernel_spells_addresses():
    assert parse_endpoint("tcp/127.0.0.1:7447") == ("127.0.0.1", 7447)
    assert parse_endpoint("tls/[::1]:7447?iface=lo") == ("::1", 7447)
    assert parse_endpoint("tcp/[::ffff:10.0.0.2]:80#x") == ("10.0.0.2", 80)  # IPv4-mapped: the IPv4 address
    assert canonical("0:0:0:0:0:0:0:1", 5) == ("::1", 5)
    for bad in ("127.0.0.1:7447", "tcp/127.0.0.1", "tcp/127.0.0.1:http", ""):
        assert parse_endpoint(bad) is None, bad


LINK = {ZID_LAPTOP: [("tcp/127.0.0.1:7000", "tcp/127.0.0.1:41000")]}
PAIR = (("127.0.0.1", 7000), ("127.0.0.1", 41000))


def test_each_connection_adds_what_it_carried_since_the_last_reading_and_a_reconnection_goes_on_adding():
    traffic = LinkTraffic()
    assert traffic.poll(LINK, {PAIR: ("socket:[1]", SocketTotals(1000, 400, 52, 52))}) == {ZID_LAPTOP: (1052, 452)}
    assert traffic.poll(LINK, {PAIR: ("socket:[1]", SocketTotals(1500, 400, 104, 52))}) == {ZID_LAPTOP: (1604, 452)}
    # the connection closed and the session reconnected (a new socket, counting from 0 again)
    assert traffic.poll(LINK, {PAIR: ("socket:[2]", SocketTotals(300, 100))}) == {ZID_LAPTOP: (1904, 552)}
    assert traffic.payload_by_peer[ZID_LAPTOP] == (1800, 500)
    assert traffic.packets_by_peer[ZID_LAPTOP] == (0, 0)  # these readings counted no segment
    assert traffic.poll(LINK, {PAIR: ("socket:[2]", SocketTotals(400, 100, segments_sent=3, segments_received=2))})
    assert traffic.packets_by_peer[ZID_LAPTOP] == (3, 2)
    # a socket no Zenoh link names (the proxy's, an operator's): counted apart, never as the link
    other = (("127.0.0.1", 5000), ("127.0.0.1", 6000))
    assert traffic.poll(LINK, {PAIR: ("socket:[2]", SocketTotals(400, 100)), other: ("socket:[3]", SocketTotals(9, 9))}) \
        == {ZID_LAPTOP: (2004, 552)}
    assert traffic.unattributed == (9, 9)


def test_a_socket_missing_from_one_reading_adds_only_its_growth_when_read_again():
    traffic = LinkTraffic()
    traffic.poll(LINK, {PAIR: ("socket:[1]", SocketTotals(1000, 400))})
    traffic.poll(LINK, {})  # not listed this time (its descriptor changed between listing and reading)
    assert traffic.poll(LINK, {PAIR: ("socket:[1]", SocketTotals(1200, 400))}) == {ZID_LAPTOP: (1200, 400)}
    for _ in range(KEEP_UNSEEN_READINGS):  # gone for good: forgotten, so the table does not grow
        traffic.poll(LINK, {})
    assert traffic.poll(LINK, {}) == {ZID_LAPTOP: (1200, 400)}
    # forgotten: the same socket seen again counts as new, from 0 (its whole totals added), where
    # one still remembered would add only its growth (100 B)
    assert traffic.poll(LINK, {PAIR: ("socket:[1]", SocketTotals(1300, 400))}) == {ZID_LAPTOP: (2500, 800)}


@pytest.mark.skipif(not supported(), reason="reads TCP_INFO through /proc (Linux)")
def test_the_kernel_counts_a_connections_payload_and_its_segments_headers():
    with socket.create_server(("127.0.0.1", 0)) as server:
        client = socket.create_connection(server.getsockname())
        accepted, _ = server.accept()
        with client, accepted:
            client.sendall(b"x" * 50_000)
            got = 0
            while got < 50_000:
                got += len(accepted.recv(65536))
            ours, theirs = client.getsockname(), client.getpeername()
            _, totals = tcp_connections()[(canonical(*ours), canonical(*theirs))]
            assert totals.payload_sent == 50_000 and totals.payload_received == 0
            assert 0 < totals.headers_sent <= 52 * 60 and totals.sent == 50_000 + totals.headers_sent
            assert 0 < totals.segments_sent <= 60 and totals.headers_sent % totals.segments_sent == 0  # each its headers
            _, mirror = tcp_connections()[(canonical(*theirs), canonical(*ours))]
            assert mirror.payload_received == 50_000


# ---- control_meter -------------------------------------------------------------------------------------


def test_control_is_what_the_link_carried_beyond_the_chain_packets_never_negative_never_twice():
    meter = ControlPlaneMeter()
    assert meter.learn_zid("laptop", ZID_LAPTOP)
    meter.note_data("laptop", "send", 10_000)
    # the kernel has not sent the packet yet when it is read: no control, and no negative charge
    assert meter.measure({ZID_LAPTOP: (4_000, 700)}) == [("laptop", "receive", 700)]
    assert meter.measure({ZID_LAPTOP: (10_600, 700)}) == [("laptop", "send", 600)]
    assert meter.measure({ZID_LAPTOP: (10_600, 700)}) == []  # nothing new: nothing charged again
    assert meter.control_bytes() == (600, 700) and meter.link_bytes() == (10_600, 700)
    # a session no status has named yet waits; its bytes are charged once one does
    assert meter.measure({ZID_LAPTOP: (10_600, 700), ZID_R2: (50, 60)}) == []
    assert meter.learn_zid("r2", ZID_R2)
    assert sorted(meter.measure({ZID_LAPTOP: (10_600, 700), ZID_R2: (50, 60)})) == \
        [("r2", "receive", 60), ("r2", "send", 50)]


def test_a_session_id_is_taken_only_from_its_own_node_and_only_as_a_zenoh_id():
    meter = ControlPlaneMeter()
    assert not meter.learn_zid("r1", "not hex!") and not meter.learn_zid("r1", "a" * 33)
    assert meter.learn_zid("r1", ZID_R2)
    assert not meter.learn_zid("r3", ZID_R2)  # claimed by two nodes: attributed to neither
    assert meter.conflicts == 1 and meter.measure({ZID_R2: (100, 100)}) == []
    assert not meter.learn_zid("r1", ZID_R2)
    assert meter.learn_zid("r1", ZID_LAPTOP)  # a restarted node: a new session, the old one stays its own


def test_a_robot_pays_its_control_bytes_on_the_radio_of_each_link_apart_from_the_model():
    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    team.join()
    team.run_until(5.0)
    r1 = team.nodes["r1"]
    r1.on_peer_status(dataclasses.replace(team.nodes["laptop"].status(1.0), zid=ZID_LAPTOP))  # its session
    medium = r1.plan_view.network.medium_between("r1", "laptop")
    sent_data = r1.control_plane.data.get(("laptop", "send"), 0)
    received_data = r1.control_plane.data.get(("laptop", "receive"), 0)
    r1.meter.advance(r1.now())
    before = dict(r1.meter.energy_j)
    r1.metering.charge_control({ZID_LAPTOP: (sent_data + 20_000, received_data + 8_000)})
    radio = SC.radios[medium]
    part = r1.meter.energy_j[f"{medium}:control"]
    assert part == pytest.approx(radio.send_w * airtime_s(20_000, radio) + radio.receive_w * airtime_s(8_000, radio))
    assert r1.meter.overhead_j()["control"] == pytest.approx(part)  # outside the model's steady state
    # the radio was busy that long: not sleeping (as for any message)
    slept = r1.meter.energy_j[f"{medium}:sleep"] - before[f"{medium}:sleep"]
    assert slept == pytest.approx(-radio.sleep_w * (airtime_s(20_000, radio) + airtime_s(8_000, radio)))
    status = r1.status(1.0)
    assert status.control_bytes == (20_000, 8_000)
    assert status.link_bytes == (sent_data + 20_000, received_data + 8_000)
    assert status.energy_j[f"{medium}:control"] == pytest.approx(part)


def test_before_the_mission_the_bytes_only_set_where_counting_starts():
    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    r1 = team.nodes["r1"]
    r1.control_plane.learn_zid("laptop", ZID_LAPTOP)
    r1.metering.charge_control({ZID_LAPTOP: (5_000, 5_000)})  # joining: no meter yet
    team.join()
    team.run_until(2.0)
    r1.metering.charge_control({ZID_LAPTOP: (5_000 + r1.control_plane.data.get(("laptop", "send"), 0) + 100,
                                    5_000 + r1.control_plane.data.get(("laptop", "receive"), 0))})
    assert r1.control_plane.control_bytes() == (100, 0)
    assert r1.control_plane.link_bytes()[0] == r1.control_plane.data[("laptop", "send")] + 100


def test_a_node_reports_the_packets_its_links_carried_since_the_mission_started():
    """What a radio carries as packets (TCP segments, bare acknowledgements too), per peer session
    its status names, from the mission's start on: `up --json`'s `links` and bench_fleet show it."""
    from autopower.launch.summary import link_totals

    team = SimTeam(SC, config=CoordinatorConfig(speed=1.0, auto_replan=False))
    r1 = team.nodes["r1"]
    r1.control_plane.learn_zid("laptop", ZID_LAPTOP)
    r1.metering.charge_control({ZID_LAPTOP: (5_000, 5_000)}, {ZID_LAPTOP: (40, 30), "c3" * 16: (7, 7)})  # joining
    team.join()
    team.run_until(2.0)
    r1.metering.charge_control({ZID_LAPTOP: (6_000, 6_000)}, {ZID_LAPTOP: (52, 33), "c3" * 16: (9, 9)})
    status = r1.status(1.0)
    assert status.link_packets == (12, 3)  # since the mission started; a session no one named is not counted
    links = link_totals(dataclasses.asdict(status))
    assert (links["packets_sent"], links["packets_received"]) == (12, 3)
    assert links["bytes_sent"] == status.link_bytes[0] and links["control_bytes_sent"] == status.control_bytes[0]
