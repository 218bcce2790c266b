"""Hostile cases against a team started the default way (mutual TLS, default-deny access control).

Real processes, real Zenoh sessions on 127.0.0.1. Every attack here worked on the code before
access control (see issue 11): a stranger joined and commanded the team, a forged high-epoch
plan stopped every source, a forged "depleted" status killed a healthy robot for good. Each test
first checks that its attacker's session really is connected where it matters, so "nothing
happened" cannot come from an attacker that never arrived.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import pytest

from autopower.cli.options import build_scenario
from autopower.deploy.pki import TeamCA
from autopower.launch.localhost import LocalTeam, TeamSpec, endpoint
from autopower.protocol import Keys, MigrateOut, NodeStatus, PlanUpdate, SnapshotRequest, decode, encode
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings
from tests.integration.runtime_helpers import sources_of, wait_for

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    spec = TeamSpec(scenario="paper-fig7", speed=5.0, auto_replan=False, lease_ms=1000,
                    log_dir=tmp_path_factory.mktemp("secure-team"))
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
    return endpoint(team.ports[team.scenario.basestation], scheme="tls")


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


def test_plain_tcp_to_a_tls_port_is_refused(team):
    import zenoh

    plain = endpoint(team.ports[team.scenario.basestation], scheme="tcp")
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
        eps = tuple(endpoint(team.ports[n], scheme="tls") for n in team.nodes if n != identity)
        self.bus = ZenohBus(ZenohSettings(connect=eps, tls=team.identities.files(identity)))
        self.expected = len(eps)
        self.latest: dict[str, bytes] = {}
        self._lock = threading.Lock()
        self.bus.subscribe(self.keys.plan, self._keep)
        self.bus.subscribe(self.keys.status_all, self._keep)

    def _keep(self, key: str, payload: bytes) -> None:
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


def _counts(team) -> dict[str, int]:
    return {c: s["produced_total"] for c, s in sources_of(team.snapshot()).items()}


def test_a_robot_identity_cannot_publish_a_plan_or_a_migration_order(team):
    snap = team.snapshot()
    epoch, placement = snap["epoch"], dict(snap["placement"])
    insider = Insider(team)
    try:
        insider.wait_connected()
        real = decode(insider.wait_for(insider.keys.plan), PlanUpdate)
        # what stopped every source before: a higher epoch with nothing running (and, since plans are
        # ordered by incarnation first, a higher incarnation: a base station taking over)
        forged = dataclasses.replace(real, epoch=real.epoch + 1000, incarnation=real.incarnation + 1000,
                                     leader="forged", running={}, placement={})
        stage, host = next(iter(placement.items()))
        order = MigrateOut(stage=stage, generation=10**9, to_node="r2")
        for _ in range(5):
            insider.bus.publish(insider.keys.plan, encode(forged))
            for node in team.nodes:
                insider.bus.publish(insider.keys.node_control(node), encode(order))
            time.sleep(0.1)
        produced = _counts(team)
        later = wait_for(team, lambda s: all(v["produced_total"] > produced[c] + 5 for c, v in sources_of(s).items()),
                         20, "every source to keep producing after the forged plan")
    finally:
        insider.close()
    assert later["epoch"] == epoch, "the forged plan was adopted"
    assert dict(later["placement"]) == placement, "a forged migration order moved a stage"
    for name, info in later["robots"].items():
        assert info["status"]["plan_epoch"] == epoch, f"{name} runs a plan the base station did not make"


def test_forged_statuses_do_not_mark_a_healthy_robot_depleted(team):
    insider = Insider(team)
    try:
        insider.wait_connected()
        real = decode(insider.wait_for(insider.keys.status("r1")), NodeStatus)
        dead = dataclasses.replace(real, depleted=True, battery_j=0.0, t_unix=time.time() + 3600)
        for _ in range(5):
            insider.bus.publish(insider.keys.status("r1"), encode(dead))  # r1's key: the ACL drops it
            insider.bus.publish(insider.keys.status("r2"), encode(dead))  # r2's own key, naming r1: dropped as forged
            time.sleep(0.1)
        time.sleep(1.5)
    finally:
        insider.close()
    snap = team.snapshot()
    r1 = snap["robots"]["r1"]
    assert r1["present"] and not r1["status"]["depleted"] and r1["status"]["battery_j"] > 0
    # and its real statuses still count: a newer one arrives after the forgery
    t_before = r1["status"]["t_unix"]
    later = wait_for(team, lambda s: s["robots"]["r1"]["status"]["t_unix"] > t_before + 0.5, 10,
                     "r1's real statuses to keep being taken")
    assert not later["robots"]["r1"]["status"]["depleted"]
    assert (later.get("basestation") or {}).get("errors", {}).get("forged", 0) >= 1, \
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
