"""The in-memory Bus (unit tests' transport) and key matching; ZenohBus config building."""

import pytest

from autopower.runtime.bus import InMemoryHub, ZenohSettings, key_matches


@pytest.mark.parametrize("pattern, key, expected", [
    ("a/b", "a/b", True),
    ("a/*", "a/b", True),
    ("a/*", "a/b/c", False),
    ("a/**", "a/b/c", True),
    ("a/**", "a", True),
    ("a/**/c", "a/c", True),
    ("a/**/c", "a/x/y/c", True),
    ("a/*/c", "a/b/d", False),
    ("*/b", "a/b", True),
])
def test_key_matches(pattern, key, expected):
    assert key_matches(pattern, key) is expected


def test_key_matches_agrees_with_zenoh():
    import zenoh

    cases = [("a/*", "a/b"), ("a/**", "a/b/c"), ("a/*/c", "a/b/d"), ("a/**/c", "a/x/y/c"), ("x/*", "x/y/z")]
    for pattern, key in cases:
        assert key_matches(pattern, key) == zenoh.KeyExpr(pattern).intersects(key)


def test_publish_subscribe_and_close():
    hub = InMemoryHub()
    a, b = hub.bus("a"), hub.bus("b")
    got = []
    handle = b.subscribe("t/*", lambda k, p: got.append((k, p)))
    a.publish("t/x", b"1")
    a.publish("u/x", b"2")
    assert got == [("t/x", b"1")]
    handle.close()
    a.publish("t/x", b"3")
    assert got == [("t/x", b"1")]


def test_deferred_delivery_with_pump():
    hub = InMemoryHub(synchronous=False)
    a = hub.bus("a")
    got = []
    a.subscribe("k", lambda k, p: got.append(p))
    a.publish("k", b"1")
    a.publish("k", b"2")
    assert got == []
    assert hub.pump() == 2
    assert got == [b"1", b"2"]


def test_liveliness_history_and_close():
    hub = InMemoryHub()
    a, b = hub.bus("a"), hub.bus("b")
    a.declare_token("alive/a")
    seen = []
    b.watch_liveliness("alive/*", lambda k, alive: seen.append((k, alive)))
    assert seen == [("alive/a", True)]  # history: tokens already present
    c = hub.bus("c")
    handle = c.declare_token("alive/c")
    handle.close()
    a.close()  # closing a bus undeclares its tokens
    assert seen == [("alive/a", True), ("alive/c", True), ("alive/c", False), ("alive/a", False)]


def test_query_reply():
    hub = InMemoryHub()
    server, client = hub.bus("s"), hub.bus("c")

    def serve(request):
        request.reply(b"re:" + request.payload)
        request.close()

    server.serve("op", serve)
    assert client.query("op", b"x") == [b"re:x"]
    server.close()
    assert client.query("op", b"x") == []


def test_zenoh_settings_config_is_loopback_only():
    import json

    cfg = ZenohSettings(listen=("tcp/127.0.0.1:1",), connect=("tcp/127.0.0.1:2",), lease_ms=500).to_config()

    def get(key):
        return json.loads(cfg.get_json(key))

    assert get("scouting/multicast/enabled") is False
    assert get("scouting/gossip/enabled") is False
    assert get("transport/link/tx/lease") == 500
    assert get("listen/endpoints") == ["tcp/127.0.0.1:1"]
    assert get("connect/endpoints") == ["tcp/127.0.0.1:2"]
