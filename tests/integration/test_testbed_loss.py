"""Per-direction packet loss and one-way cuts on testbed links: `autopower fault loss|cut --one-way`.

The namespace tests build real namespaces and links with the testbed's own `NamespaceNetwork`
and inject the faults through the same `FaultController` the `testbed up` supervisor serves;
UDP datagrams then show which direction passes (a ping cannot: its reply crosses the other
direction). They need root and nftables' `nft` (CI runs as root); without either they fail with
that reason rather than pass. Each network is built in a `with` block, so it is removed also when
an assertion fails, and the `clean` fixture checks nothing is left. Every wait has a deadline.

The CLI tests run the installed `autopower` against a supervisor's control socket served by this
test (no team processes, no root): bad input is exit 2 with a message saying what to do.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import pytest

from autopower.launch.faults import SOCKET_NAME, FaultController, FaultServer
from autopower.launch.localhost import LocalTeam
from autopower.launch.netns import NFT_TABLE, NamespaceNetwork
from autopower.launch.testbed import _LinkSwitch
from autopower.model.loading import load_scenario
from autopower.model.network import Link, Network, build_network
from tests.e2e.test_testbed import clean, root  # noqa: F401 - fixtures
from tests.e2e.test_up import AUTOPOWER

PORT = 7601
PROBES = 200


@pytest.fixture
def nft(root):  # noqa: F811
    if shutil.which("nft") is None:
        pytest.fail("these tests need nftables' `nft` tool (Debian: apt-get install nftables)")


class Team:
    """What `FaultController` uses of a team for link faults, over the given links."""

    proxy = LocalTeam.proxy  # the real lookup, with its error for an unknown node or link

    def __init__(self, nodes, proxies):
        self.nodes, self.proxies = list(nodes), proxies
        self.spec = SimpleNamespace(record_dir=None)

    def supervision(self) -> dict:
        return {}


def team_of(net: NamespaceNetwork) -> Team:
    return Team(net.nodes, {frozenset((l.a, l.b)): _LinkSwitch(net, l.a, l.b) for l in net.links})


def two_nodes(tmp_path) -> NamespaceNetwork:
    """Two nodes and one 802.11a link between them: a shaped veth pair, as the testbed makes it."""
    scenario = load_scenario("paper-fig7")
    network = Network(["a", "b"], "a", [Link(a="a", b="b", medium="802.11a", group="a-b")])
    return NamespaceNetwork(network, scenario.radios, speed=1.0, state_dir=tmp_path)


def bridged(tmp_path) -> NamespaceNetwork:
    """paper-fig7's four nodes on one 802.11a bridge (a shared medium)."""
    scenario = load_scenario("paper-fig7")
    return NamespaceNetwork(build_network(scenario), scenario.radios, speed=1.0, state_dir=tmp_path)


RECEIVER = """
    import select, socket, sys
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("0.0.0.0", {port}))
    print("ready", flush=True)
    seen = set()
    while True:  # until stdin closes (the sender is done) or nothing happens for 10 s
        ready, _, _ = select.select([s, sys.stdin], [], [], 10.0)
        if s in ready:
            seen.add(s.recv(64))
        if sys.stdin in ready or not ready:
            break
    s.setblocking(False)
    while True:  # what arrived before the stop
        try:
            seen.add(s.recv(64))
        except BlockingIOError:
            break
    print(len(seen), flush=True)
"""

SENDER = """
    import socket, time
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range({count}):
        s.sendto(b"probe %d" % i, ("{address}", {port}))
        time.sleep(0.002)  # paced: no queue on the way may overflow, so only the rule drops
"""


def delivered(net: NamespaceNetwork, src: str, dst: str, count: int = 20) -> int:
    """How many of ``count`` distinct UDP datagrams ``src`` sends over its link to ``dst`` arrive."""
    def in_ns(node, code):
        return ["ip", "netns", "exec", net.ns(node), sys.executable, "-c", textwrap.dedent(code)]

    receiver = subprocess.Popen(in_ns(dst, RECEIVER.format(port=PORT)), stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)
    try:
        assert select.select([receiver.stdout], [], [], 20)[0], "the receiver did not start"
        assert receiver.stdout.readline().strip() == "ready"
        address = net.peer_address(src, dst)
        subprocess.run(in_ns(src, SENDER.format(count=count, address=address, port=PORT)), check=True, timeout=30)
        time.sleep(0.3)  # the last datagrams cross the link
        out, _ = receiver.communicate(input="", timeout=20)
        return int(out.split()[-1])
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait()


def tables(net: NamespaceNetwork, node: str) -> str:
    return subprocess.run(["ip", "netns", "exec", net.ns(node), "nft", "list", "tables"], capture_output=True,
                          text=True, timeout=10, check=True).stdout


@pytest.mark.slow
@pytest.mark.parametrize("medium", ["veth", "bridge"])
@pytest.mark.parametrize("fault", [{"op": "loss", "pct": 100}, {"op": "cut"}], ids=["loss-100", "cut"])
def test_one_way_drops_only_a_to_b_and_heal_brings_both_back(tmp_path, clean, nft, medium, fault):  # noqa: F811
    net = two_nodes(tmp_path) if medium == "veth" else bridged(tmp_path)
    a, b = ("a", "b") if medium == "veth" else ("r1", "laptop")
    with net:
        controller = FaultController(team_of(net))
        assert delivered(net, a, b) == 20 and delivered(net, b, a) == 20

        reply = controller.apply({**fault, "a": a, "b": b, "one_way": True})
        assert reply["fault"]["direction"] == f"{a}->{b}"
        assert delivered(net, a, b) == 0
        assert delivered(net, b, a) == 20
        shown = "loss 100%" if fault["op"] == "loss" else "cut"
        assert controller.apply({"op": "list"})["links"][f"{min(a, b)}-{max(a, b)}"] == f"{shown} {a}->{b}"
        if medium == "bridge":  # the node's other links on that medium are untouched
            assert delivered(net, "r2", "laptop") == 20

        controller.apply({"op": "heal", "a": a, "b": b})
        assert delivered(net, a, b) == 20 and delivered(net, b, a) == 20
        assert controller.apply({"op": "list"})["links"][f"{min(a, b)}-{max(a, b)}"] == "up"
        assert NFT_TABLE not in tables(net, a) + tables(net, b)  # a healed node holds no rules at all
        assert [f["kind"] for f in controller.log] == [fault["op"], "heal"]


@pytest.mark.slow
def test_half_the_packets_are_lost_at_random(tmp_path, clean, nft):  # noqa: F811
    net = two_nodes(tmp_path)
    with net:
        controller = FaultController(team_of(net))
        controller.apply({"op": "loss", "a": "a", "b": "b", "pct": 50, "one_way": True})
        # each datagram is dropped independently with p = 0.5: delivered ~ Binomial(200, 0.5),
        # mean 100, sd sqrt(200 * 0.25) = 7.1; 65..135 is ±4.9 sd, so a correct rule fails this
        # about once in a million runs, while a rule that drops all, none, or one in four or
        # three in four (50 or 150 expected) lands outside it almost surely
        got = delivered(net, "a", "b", PROBES)
        assert 65 <= got <= 135, f"{got} of {PROBES} datagrams arrived at 50 % loss"
        assert delivered(net, "b", "a", PROBES) == PROBES  # one way only

        controller.apply({"op": "loss", "a": "a", "b": "b", "pct": 50})  # both ways
        assert controller.apply({"op": "list"})["links"]["a-b"] == "loss 50% a->b, loss 50% b->a"
        controller.apply({"op": "heal", "a": "a", "b": "b"})
        assert delivered(net, "a", "b", PROBES) == PROBES


# ---- the CLI against bad input ----------------------------------------------------------------------


class LoopbackLink:
    """A localhost team's link (a `LinkProxy`'s face): it can only cut both ways."""

    is_cut = False

    def cut(self) -> None:
        self.is_cut = True

    def heal(self) -> None:
        self.is_cut = False


@pytest.fixture(params=["testbed", "localhost"])
def served(request, tmp_path, monkeypatch):
    """A running team's control socket and session file, served here; yields (kind, env)."""
    from autopower.basestation.operator import team_dir, write_session

    monkeypatch.setenv("AUTOPOWER_STATE_DIR", str(tmp_path / "state"))
    scenario = load_scenario("paper-fig7")
    if request.param == "testbed":  # its network is described, never created: no root needed
        team = team_of(NamespaceNetwork(build_network(scenario), scenario.radios, speed=1.0,
                                             state_dir=tmp_path))
    else:
        nodes = ["r1", "r2", "r3", "laptop"]  # in the order the scenario lists them
        team = Team(nodes, {frozenset((x, y)): LoopbackLink() for i, x in enumerate(nodes) for y in nodes[i + 1:]})
    with FaultServer(FaultController(team), team_dir("t") / SOCKET_NAME) as server:
        write_session({"team": "t", "pid": os.getpid(), "control": str(server.path)})
        yield request.param, {**os.environ, "PYTHONUNBUFFERED": "1"}


def fault(env, *args) -> subprocess.CompletedProcess:
    return subprocess.run([AUTOPOWER, "fault", *args], env=env, capture_output=True, text=True, timeout=60)


def test_fault_loss_names_an_unknown_robot(served):
    _kind, env = served
    result = fault(env, "loss", "r9", "laptop", "30")
    assert result.returncode == 2, result.stderr
    assert "unknown node 'r9'; nodes of this team: r1, r2, r3, laptop" in result.stderr


@pytest.mark.parametrize("pct", ["0", "-5", "100.5", "thirty"])
def test_fault_loss_refuses_a_percentage_out_of_range(served, pct):
    _kind, env = served
    result = fault(env, "loss", "r1", "laptop", "--", pct)
    assert result.returncode == 2
    assert "Invalid value for 'PCT'" in result.stderr
    assert pct == "thirty" or f"{float(pct)} is not in the range 0<x<=100" in result.stderr, result.stderr


@pytest.mark.parametrize("served", ["localhost"], indirect=True)
@pytest.mark.parametrize("args", [["loss", "r1", "laptop", "30"], ["cut", "r1", "laptop", "--one-way"]])
def test_a_localhost_team_refuses_one_way_faults_it_cannot_do(served, args):
    _kind, env = served
    result = fault(env, *args)
    assert result.returncode == 2
    assert "needs the testbed (`sudo autopower testbed up`)" in result.stderr, result.stderr
    listed = json.loads(fault(env, "list").stdout)
    assert listed["faults"] == [] and set(listed["links"].values()) == {"up"}  # nothing half done
