"""Hostile cases against a team started the default way (mutual TLS, default-deny access control).

Real processes, real Zenoh sessions on 127.0.0.1. Every attack here worked on the code before
access control (see issue 11): a stranger joined and commanded the team, a forged high-epoch
plan stopped every source, a forged "depleted" status killed a healthy robot for good. Each test
first checks that its attacker's session really is connected where it matters, so "nothing
happened" cannot come from an attacker that never arrived. Where Zenoh's access control is what
must stop a forgery, a `Witness` on every node shows that no node's Zenoh delivered it, so a check
in the processes cannot stand in for the access control unnoticed.

Every test runs twice: the team's links over TLS (TCP), and over Zenoh's QUIC link, which reads
the same certificates and whose access control must refuse the same identities.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from contextlib import ExitStack

import pytest

from autopower.cli.options import build_scenario
from autopower.deploy.pki import TeamCA
from autopower.launch.localhost import LocalTeam, TeamSpec, endpoint
from autopower.protocol import Keys, MigrateOut, NodeStatus, PlanUpdate, SnapshotRequest, StatusDelta, decode, encode
from autopower.protocol.access import status_problem
from autopower.protocol.codec import message_kind
from autopower.protocol.statuses import KEY_EVERY_S
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings
from tests.integration.runtime_helpers import sinks_of, sources_of, wait_for

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", params=["tls", "quic"])
def team(request, tmp_path_factory):
    spec = TeamSpec(scenario="paper-fig7", speed=5.0, auto_replan=False, lease_ms=1000,
                    log_dir=tmp_path_factory.mktemp(f"secure-team-{request.param}"), transport=request.param)
    team = LocalTeam(spec, build_scenario("paper-fig7"))
    assert team.identities is not None, "a team must be secure by default"
    team.__enter__()
    try:
        team.wait_ready(90)
        yield team
    finally:
        codes = team.stop()
        assert all(c == 0 for c in codes.values()), (codes, team.log_dir)


def open_client(settings: ZenohSettings):
    """A client-mode session that fails fast (raises) when the listener refuses it."""
    import zenoh

    cfg = dataclasses.replace(settings, mode="client").to_config()
    cfg.insert_json5("connect/timeout_ms", "3000")
    cfg.insert_json5("connect/exit_on_failure", "true")
    return zenoh.open(cfg)


def base_tls(team) -> str:
    """The base station's secure endpoint (tls/... or quic/..., the team's transport)."""
    assert team.scheme in ("tls", "quic"), team.scheme
    return endpoint(team.ports[team.scenario.basestation], scheme=team.scheme)


# ---- who may connect -------------------------------------------------------------------------------


def test_the_operator_identity_connects_and_is_answered(team):
    """The positive control for the refusals below: same endpoint, the right certificate."""
    session = open_client(ZenohSettings(connect=(base_tls(team),), tls=team.identities.files("operator")))
    try:
        replies = [r for r in session.get(Keys(team.team).operator, payload=encode(SnapshotRequest()), timeout=3.0)
                   if r.ok is not None]
        assert replies, "the operator identity got no answer"
    finally:
        session.close()


def test_no_client_certificate_is_refused(team):
    import zenoh

    mine = team.identities.files("operator")
    settings = ZenohSettings(connect=(base_tls(team),), tls=mine)
    cfg = dataclasses.replace(settings, mode="client").to_config()
    # server-authenticated TLS only: the client trusts the CA but presents no certificate
    cfg.insert_json5("transport/link/tls/enable_mtls", "false")
    cfg.insert_json5("connect/timeout_ms", "3000")
    cfg.insert_json5("connect/exit_on_failure", "true")
    with pytest.raises(zenoh.ZError):
        zenoh.open(cfg).close()


def test_a_certificate_from_another_ca_is_refused(team, tmp_path):
    import zenoh

    other = TeamCA.create(tmp_path / "ca", "evil")
    stranger = other.issue("operator", ["127.0.0.1"], tmp_path)  # even the right name
    tls = TlsFiles(ca=str(team.identities.files("operator").ca), cert=str(stranger.cert), key=str(stranger.key))
    with pytest.raises(zenoh.ZError):
        open_client(ZenohSettings(connect=(base_tls(team),), tls=tls)).close()


def test_a_plain_link_to_a_secure_port_is_refused(team):
    """Zenoh's link without TLS on the same port: tcp to a TLS listener, udp to a QUIC one."""
    import zenoh

    plain = endpoint(team.ports[team.scenario.basestation], scheme={"tls": "tcp", "quic": "udp"}[team.scheme])
    with pytest.raises(zenoh.ZError):
        open_client(ZenohSettings(connect=(plain,))).close()


def test_an_operator_command_from_a_robot_identity_is_refused(team):
    session = open_client(ZenohSettings(connect=(base_tls(team),), tls=team.identities.files("r1")))
    try:
        replies = [r for r in session.get(Keys(team.team).operator, payload=encode(SnapshotRequest()), timeout=2.0)
                   if r.ok is not None]
        assert replies == [], "a robot's identity was answered on the operator key"
    finally:
        session.close()


# ---- what an authenticated robot may not do ----------------------------------------------------------


class Insider:
    """A second session holding robot r2's certificate, connected as a peer to every node."""

    def __init__(self, team, identity: str = "r2"):
        self.keys = Keys(team.team)
        eps = tuple(endpoint(team.ports[n], scheme=team.scheme) for n in team.nodes if n != identity)
        self.bus = ZenohBus(ZenohSettings(connect=eps, tls=team.identities.files(identity)))
        self.expected = len(eps)
        self.latest: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self.bus.subscribe(self.keys.plan, self._keep)
        self.bus.subscribe(self.keys.status_all, self._keep)

    def _keep(self, key: str, payload: bytes) -> None:
        if message_kind(payload) == StatusDelta.KIND:
            return  # a status's change from its whole one: the insider copies whole ones
        with self._lock:
            self.latest[key] = payload

    def wait_connected(self, timeout_s: float = 15.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if len(list(self.bus.session.info.peers_zid())) >= self.expected:
                return
            time.sleep(0.1)
        raise AssertionError(f"the insider reached {len(list(self.bus.session.info.peers_zid()))} of "
                             f"{self.expected} nodes")

    def wait_for(self, key: str, timeout_s: float = 10.0) -> bytes:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                if key in self.latest:
                    return self.latest[key]
            time.sleep(0.05)
        raise AssertionError(f"the insider never saw {key} (it may read the team's traffic)")

    def close(self) -> None:
        self.bus.close()


class Witness:
    """What each node's Zenoh lets through, with no application code in between.

    One client session per node, attached to that node alone and holding the base station's
    certificate (a member, so it may subscribe). A node hands its clients what it accepted from its
    peers: after its ingress access control, before any process reads it. A forged put that no
    witness receives was stopped by Zenoh itself, whatever the processes would have made of it; a
    put some witness receives got past Zenoh, so whatever then ignores it is the application's check.
    """

    def __init__(self, team, *key_exprs: str):
        self.keys = Keys(team.team)
        self.nodes = tuple(team.nodes)
        self.seen: list[tuple[str, str, bytes]] = []  # (the node attached to, key, payload)
        self._statuses: list[tuple[str, NodeStatus | StatusDelta]] = []  # (the node attached to, status)
        self._lock = threading.Lock()
        self._sessions = []
        self._subscribers = []
        try:
            for node in self.nodes:
                session = open_client(ZenohSettings(connect=(endpoint(team.ports[node], scheme=team.scheme),),
                                                    tls=team.identities.files(team.scenario.basestation)))
                self._sessions.append(session)
                for expr in (self.keys.status_all, *key_exprs):
                    self._subscribers.append(session.declare_subscriber(
                        expr, lambda sample, node=node: self._keep(node, str(sample.key_expr),
                                                                   sample.payload.to_bytes())))
        except BaseException:
            self.close()
            raise

    def _keep(self, node: str, key: str, payload: bytes) -> None:
        # whole or as its change from a whole one: either names its node and time
        status = decode(payload, (NodeStatus, StatusDelta)) if self.keys.node_of_status(key) is not None else None
        with self._lock:
            self.seen.append((node, key, payload))
            if status is not None:
                self._statuses.append((node, status))

    def statuses(self, node: str) -> list[NodeStatus | StatusDelta]:
        with self._lock:
            return [st for n, st in self._statuses if n == node]

    def wait_forwarding(self, timeout_s: float = 15.0) -> None:
        """The positive control: every node hands its witness the statuses of other nodes, which
        reach it from its peers over the very path a forged put from a peer would take."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(any(st.node != node for st in self.statuses(node)) for node in self.nodes):
                return
            time.sleep(0.1)
        raise AssertionError(f"no statuses of other nodes reached the witnesses on "
                             f"{[n for n in self.nodes if not any(st.node != n for st in self.statuses(n))]}")

    def wait_status_after(self, of: str, t_unix: float, timeout_s: float = 15.0) -> None:
        """Until every witness has a status of ``of`` stamped after ``t_unix``: a put sent before that
        status has had its chance to arrive everywhere."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(any(st.node == of and st.t_unix > t_unix for st in self.statuses(n)) for n in self.nodes):
                return
            time.sleep(0.1)
        raise AssertionError(f"{of}'s statuses stopped reaching the witnesses")

    def carried(self, payloads: set[bytes]) -> list[tuple[str, str]]:
        """(node, key) of every delivery of one of ``payloads``."""
        with self._lock:
            return sorted({(n, k) for n, k, p in self.seen if p in payloads})

    def close(self) -> None:
        for session in self._sessions:
            session.close()
        self._sessions.clear()


def _counts(team) -> dict[str, int]:
    return {c: s["produced_total"] for c, s in sources_of(team.snapshot()).items()}


def _hosting(snap: dict) -> dict[str, tuple[dict, dict]]:
    """Every node's hosted stages: (stage -> generation of its instance, stage -> lifecycle)."""
    statuses = {name: info["status"] for name, info in snap["robots"].items() if info.get("status")}
    if snap.get("basestation"):
        statuses[snap["basestation"]["node"]] = snap["basestation"]
    return {node: (dict(st["generations"]), dict(st["hosted"])) for node, st in statuses.items()}


def _gap_free(sink: dict) -> bool:
    return sink["received"] == sink["contiguous"] == sink["max_seq"] + 1 and sink["duplicates"] == 0


def _steady(snap: dict) -> bool:
    """Every placed stage runs on its host, and every running chain's sink reports."""
    hosting = _hosting(snap)
    return all(hosting.get(host, ({}, {}))[1].get(stage) == "running" for stage, host in snap["placement"].items()) \
        and set(snap["running"]) <= set(sinks_of(snap))


def test_a_robot_identity_cannot_publish_a_plan_or_a_migration_order(team):
    snap = wait_for(team, _steady, 30, "every stage running and every sink reporting")
    epoch, placement = snap["epoch"], dict(snap["placement"])
    hosting, sinks = _hosting(snap), sinks_of(snap)
    keys = Keys(team.team)
    with ExitStack() as stack:  # every session closed, whatever fails
        witness = Witness(team, keys.plan, f"{keys.prefix}/node/*/control")
        stack.callback(witness.close)
        insider = Insider(team)
        stack.callback(insider.close)
        witness.wait_forwarding()
        insider.wait_connected()
        real = decode(insider.wait_for(insider.keys.plan), PlanUpdate)
        # what stopped every source before: a higher epoch with nothing running (and, since plans are
        # ordered by incarnation first, a higher incarnation: a base station taking over)
        forged = dataclasses.replace(real, epoch=real.epoch + 1000, incarnation=real.incarnation + 1000,
                                     leader="forged", running={}, placement={})
        # a running stage moved to another robot: its host would drain it and ship its state there
        stage, host = next((s, h) for s, h in sorted(placement.items()) if h != "r2")
        order = MigrateOut(stage=stage, generation=10**9, to_node="r2")
        for _ in range(5):
            insider.bus.publish(insider.keys.plan, encode(forged))
            for node in team.nodes:
                insider.bus.publish(insider.keys.node_control(node), encode(order))
            time.sleep(0.1)
        sent = time.time()
        produced = _counts(team)
        # bounded: every sink takes in more outputs, each without a gap, and every robot reports what it
        # hosts after the orders had arrived; the placement, every node's stages and their generations
        # must be as they were
        later = wait_for(team, lambda s: all(v["produced_total"] > produced[c] + 5 for c, v in sources_of(s).items())
                         and all(sinks_of(s)[c]["contiguous"] >= v["contiguous"] + 5 and _gap_free(sinks_of(s)[c])
                                 for c, v in sinks.items())
                         and all(i["status"]["t_unix"] > sent + 0.5 for i in s["robots"].values()),
                         30, "every source to keep producing and every sink to take in its outputs without a gap")
        witness.wait_status_after(host, sent)
    assert later["epoch"] == epoch, "the forged plan was adopted"
    assert dict(later["placement"]) == placement, "a forged migration order moved a stage"
    for name, info in later["robots"].items():
        assert info["status"]["plan_epoch"] == epoch, f"{name} runs a plan the base station did not make"
    assert _hosting(later) == hosting, f"a forged order changed what runs where ({stage} on {host})"
    for chain, before in sinks.items():
        sink = sinks_of(later)[chain]
        assert sink["run"] == before["run"] and sink["duplicates_total"] == before["duplicates_total"] \
            and sink["given_up_total"] == before["given_up_total"], (chain, before, sink)
    assert witness.carried({encode(forged), encode(order)}) == [], "Zenoh delivered a forged plan or order"


def _watched_insider(team, stack: ExitStack, key: str):
    """(witness, insider, the real status on ``key``), both sessions closed by ``stack``, once the
    witnesses see peers' statuses and the insider is connected."""
    witness = Witness(team)
    stack.callback(witness.close)
    insider = Insider(team)
    stack.callback(insider.close)
    witness.wait_forwarding()
    insider.wait_connected()
    return witness, insider, decode(insider.wait_for(key, KEY_EVERY_S + 5.0), NodeStatus)


def test_a_robot_identity_cannot_put_a_status_on_another_robots_key(team):
    """Zenoh's access control alone stops it. The forged status names r1 on r1's key and is stamped
    now, so every check the processes make (`status_problem`) would take it: the witnesses show
    that no node's Zenoh let it through, before any process could judge it. The base station's
    latest view of r1 cannot show this alone: r1's next real status replaces a forged one."""
    keys = Keys(team.team)
    forged: set[bytes] = set()
    with ExitStack() as stack:  # every session closed, whatever fails
        witness, insider, real = _watched_insider(team, stack, keys.status("r1"))
        for _ in range(5):
            dead = dataclasses.replace(real, depleted=True, battery_j=0.0, t_unix=time.time())
            assert status_problem(keys, keys.status("r1"), dead.node, dead.t_unix, time.time()) is None
            forged.add(encode(dead))
            insider.bus.publish(keys.status("r1"), encode(dead))
            time.sleep(0.1)
        witness.wait_status_after("r1", time.time() + 0.5)
    assert witness.carried(forged) == [], "Zenoh delivered a status put by r2 on r1's key"
    r1 = team.snapshot()["robots"]["r1"]
    assert r1["present"] and not r1["status"]["depleted"] and r1["status"]["battery_j"] > 0


def test_a_status_naming_another_robot_on_its_own_key_is_dropped_as_forged(team):
    """What Zenoh cannot judge: r2 may put on its own status key, and the witnesses show Zenoh
    delivering it; the status naming r1 there is dropped by the processes, so r1 stays healthy."""
    keys = Keys(team.team)
    forged_before = ((team.snapshot().get("basestation") or {}).get("errors") or {}).get("forged", 0)
    forged: set[bytes] = set()
    with ExitStack() as stack:  # every session closed, whatever fails
        witness, insider, real = _watched_insider(team, stack, keys.status("r1"))
        for _ in range(5):
            dead = dataclasses.replace(real, depleted=True, battery_j=0.0, t_unix=time.time())  # within the clock check
            forged.add(encode(dead))
            insider.bus.publish(keys.status("r2"), encode(dead))
            time.sleep(0.1)
        t_sent = time.time()
        witness.wait_status_after("r1", t_sent + 0.5)
        # r1's real statuses still count: newer ones are taken after the forgery
        later = wait_for(team, lambda s: s["robots"]["r1"]["status"]["t_unix"] > t_sent + 0.5, 10,
                         "r1's real statuses to keep being taken")
    assert (team.scenario.basestation, keys.status("r2")) in witness.carried(forged), \
        "Zenoh did not deliver r2's put on its own key: the processes' check was never tried"
    r1 = later["robots"]["r1"]
    assert r1["present"] and not r1["status"]["depleted"] and r1["status"]["battery_j"] > 0
    assert (later.get("basestation") or {}).get("errors", {}).get("forged", 0) >= forged_before + 1, \
        "the base station did not notice the status naming r1 on r2's key"


def test_a_robot_cannot_relay_a_plan_in_the_base_stations_name(team):
    """A relaying robot writes the origin of what it carries; the destination checks the origin's
    signature (end to end, the team CA's key of that node), not the relay's word."""
    from autopower.protocol import Relayed
    from autopower.runtime.signatures import Signing

    snap = team.snapshot()
    epoch = snap["epoch"]
    forged_before = ((snap["robots"]["r1"]["status"] or {}).get("errors") or {}).get("forged", 0)
    insider = Insider(team)
    files = team.identities.files("r2")
    try:
        insider.wait_connected()
        real = decode(insider.wait_for(insider.keys.plan), PlanUpdate)
        forged_plan = encode(dataclasses.replace(real, epoch=real.epoch + 1000, running={}, placement={}))
        # "from the laptop, via r2": unsigned, and signed with r2's own key
        carried = Relayed(path=("laptop", "r2", "r1"), hop=1, key=insider.keys.plan, payload=forged_plan)
        signed_by_r2 = Signing.load("r2", files.ca, files.cert, files.key).sign(carried)
        for _ in range(5):
            for msg in (carried, signed_by_r2):
                insider.bus.publish(insider.keys.node_relay("r1"), encode(dataclasses.replace(msg, hop=2)))
            time.sleep(0.1)
        produced = _counts(team)
        later = wait_for(team, lambda s: all(v["produced_total"] > produced[c] + 5 for c, v in sources_of(s).items())
                         and s["robots"]["r1"]["status"]["errors"].get("forged", 0) >= forged_before + 10,
                         20, "every source to keep producing and r1 to count the forgeries")
    finally:
        insider.close()
    assert later["epoch"] == epoch
    assert later["robots"]["r1"]["status"]["plan_epoch"] == epoch, "r1 adopted a plan relayed in the laptop's name"
