"""The team's access policy: who may put what, as Zenoh's ACL and as the processes' own checks."""

from __future__ import annotations

import pytest

from autopower.protocol import Keys, Relayed, encode
from autopower.protocol.access import OPERATOR, TeamAccess, status_problem
from autopower.runtime.access_control import zenoh_access_control
from autopower.runtime.bus import InMemoryHub, TlsFiles, ZenohSettings
from autopower.runtime.relay import Relayer

KEYS = Keys("t")
ACCESS = TeamAccess(KEYS, "laptop", ("r1", "r2"))


@pytest.mark.parametrize("identity,key,allowed", [
    ("laptop", KEYS.plan, True),
    ("laptop", KEYS.node_control("r1"), True),
    ("r1", KEYS.plan, False),  # only the base station makes plans
    ("r1", KEYS.node_control("r2"), False),  # ... and migration orders
    ("r1", KEYS.status("r1"), True),
    ("r1", KEYS.status("r2"), False),  # never another robot's status
    ("r1", KEYS.node_data("r2"), True),  # outputs and frames
    ("r1", KEYS.node_relay("r2"), True),
    ("r1", KEYS.subgroup, True),
    ("laptop", KEYS.subgroup, False),
    (OPERATOR, KEYS.plan, False),  # the operator only queries
    ("stranger", KEYS.node_data("r1"), False),
    ("laptop", KEYS.addressed("r1", "laptop"), True),  # its status as r1 acts on it, acks
    ("r2", KEYS.addressed("r1", "r2"), True),  # acknowledgements in its own name
    ("r2", KEYS.addressed("r1", "laptop"), False),  # never in the base station's
    ("laptop", KEYS.peer("laptop"), False),  # the base station addresses each robot instead
])
def test_who_may_put_what(identity, key, allowed):
    assert ACCESS.may_put(identity, key) is allowed


def test_the_zenoh_section_is_default_deny_with_one_subject_per_identity():
    acl = zenoh_access_control(ACCESS)
    assert acl["enabled"] and acl["default_permission"] == "deny"
    names = sorted(n for s in acl["subjects"] for n in s["cert_common_names"])
    assert names == sorted(["laptop", "r1", "r2", OPERATOR])
    rules = {r["id"]: r for r in acl["rules"]}
    policies = {p["subjects"][0]: set(p["rules"]) for p in acl["policies"]}
    assert rules["put-r1"]["key_exprs"] == list(ACCESS.puts("r1")) and rules["put-r1"]["flows"] == ["ingress"]
    assert "operator-serve" in policies["node-laptop"] and "operator-serve" not in policies["node-r1"]
    assert policies["operator"] == {"send", "operator-query"}


def test_tls_settings_turn_on_mtls_on_both_sides():
    files = TlsFiles(ca="ca.pem", cert="r1.pem", key="r1.key")
    tls = ZenohSettings(tls=files, access_control=zenoh_access_control(ACCESS)).to_dict()["transport"]["link"]["tls"]
    assert tls["enable_mtls"] is True  # the connecting side too, or it never sends its certificate
    assert tls["connect_certificate"] == "r1.pem" and tls["listen_private_key"] == "r1.key"
    assert "tls" not in ZenohSettings().to_dict()["transport"]["link"]


def test_a_status_must_name_its_key_and_not_come_from_the_future():
    assert status_problem(KEYS, KEYS.status("r1"), "r1", 100.0, 100.0) is None
    assert "naming 'r1' on 'r2'" in status_problem(KEYS, KEYS.status("r2"), "r1", 100.0, 100.0)
    assert "future" in status_problem(KEYS, KEYS.status("r1"), "r1", 100.0 + 3600, 100.0)
    # the base station's status addressed to one robot names the base station's key
    assert status_problem(KEYS, KEYS.addressed("r1", "laptop"), "laptop", 100.0, 100.0) is None
    assert "naming 'laptop' on 'r2'" in status_problem(KEYS, KEYS.addressed("r1", "r2"), "laptop", 100.0, 100.0)


def test_a_relayed_message_is_delivered_only_if_its_origin_may_put_on_its_key():
    hub = InMemoryHub()
    counted = []
    r1 = Relayer(node="r1", bus=hub.bus("r1"), keys=KEYS, access=ACCESS, count=lambda w, d="": counted.append(w))
    # r2 wraps a "plan" claiming to be its own origin: refused
    forged = Relayed(path=("r2", "r1"), hop=1, key=KEYS.plan, payload=b"x")
    assert r1.on_relay(encode(forged)) is None and counted == ["forged"]
    genuine = Relayed(path=("laptop", "r2", "r1"), hop=2, key=KEYS.plan, payload=b"plan")
    assert r1.on_relay(encode(genuine)) == (KEYS.plan, b"plan")
