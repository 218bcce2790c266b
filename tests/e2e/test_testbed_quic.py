"""`autopower testbed up --transport quic`: the team's links over Zenoh's QUIC link, as a user runs it.

Real namespaces and shaped links, the fleet `deploy init` would write with ``transport = "quic"``:
mutual TLS inside QUIC with the team's certificates, default-deny access control. The chains
deliver, a robot's identity is refused what only the operator may ask over the same QUIC link
the operator's identity is answered on, and a silent cut is detected within the bounds the TLS
testbed keeps (test_testbed.py). Needs root (CI runs as root). Bounded: ``--duration`` and
timeouts on every wait; every namespace is removed by the run or, when the test fails, by the
`clean` fixture.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import pytest

from autopower.launch.netns import PREFIX
from tests.e2e.test_testbed import clean, ours, root, start_testbed, stop  # noqa: F401 (fixtures)
from tests.e2e.test_up import run_cli, wait_until

pytestmark = pytest.mark.slow
NODES = ("laptop", "r1", "r2", "r3")
PORT = 7447  # `launch.testbed.PORT`

# Run inside a node's namespace: a client session over ``endpoint`` holding ``identity``'s
# certificate asks the base station's operator key; prints how many answers came.
ASK_OPERATOR_KEY = r"""
import sys
import zenoh
from autopower.deploy.pki import identity_in
from autopower.protocol import Keys, SnapshotRequest, encode
from autopower.runtime.bus import ZenohSettings
endpoint, directory, identity, team = sys.argv[1:5]
cfg = ZenohSettings(connect=(endpoint,), tls=identity_in(directory, identity), mode="client").to_config()
cfg.insert_json5("connect/timeout_ms", "10000")
cfg.insert_json5("connect/exit_on_failure", "true")
session = zenoh.open(cfg)
try:
    replies = session.get(Keys(team).operator, payload=encode(SnapshotRequest()), timeout=3.0)
    print(sum(1 for r in replies if r.ok is not None), flush=True)
finally:
    session.close()
"""


def ss(namespace: str, *args: str) -> list[str]:
    out = subprocess.run(["ip", "netns", "exec", namespace, "ss", "-H", *args], capture_output=True, text=True,
                         timeout=10, check=True)
    return [line for line in out.stdout.splitlines() if line.strip()]


def ip_address_of(namespace: str) -> str:
    """The node's one address on its links (paper-fig7: one shared 802.11a medium)."""
    out = subprocess.run(["ip", "-n", namespace, "-4", "-o", "addr", "show"], capture_output=True, text=True,
                         timeout=10, check=True)
    found = [line.split()[3].split("/")[0] for line in out.stdout.splitlines() if " lo " not in line]
    assert len(found) == 1, out.stdout
    return found[0]


def ask_operator_key(namespace: str, endpoint: str, directory, identity: str, team: str, env: dict) -> int:
    out = subprocess.run(["ip", "netns", "exec", namespace, sys.executable, "-c", ASK_OPERATOR_KEY, endpoint,
                          str(directory), identity, team], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    return int(out.stdout.strip().splitlines()[-1])


def test_a_quic_team_in_the_testbed_delivers_refuses_a_wrong_identity_and_detects_a_cut(tmp_path, clean):  # noqa: F811
    proc, session, env = start_testbed(tmp_path, "--transport", "quic", "--lease-ms", "500", "--duration", "120")
    run_id, team = session["testbed"], session["team"]
    fleet = tmp_path / "state" / "tls" / team
    try:
        # Every link between nodes is QUIC: each node listens on UDP, and no TCP connection joins
        # two nodes; the base station's TCP listener takes only the operator's bridge (loopback).
        connects = [ep for n in NODES for ep in json.loads((fleet / n / "node.json").read_text())["zenoh"]["connect"]]
        assert len(connects) == 6 and all(ep.startswith("quic/") for ep in connects), connects
        for node in NODES:
            ns = f"{PREFIX}{run_id}-{node}"
            assert ss(ns, "-ulpn", f"sport = :{PORT}"), f"{node} has no QUIC (UDP) listener on {PORT}"
            tcp = [line for line in ss(ns, "-tn", "state", "established")
                   if f":{PORT} " in f"{line} " and "127.0.0.1:" not in line]
            assert tcp == [], f"{node} has TCP links to other nodes: {tcp}"
        # Access control over QUIC: from r1's namespace, over the radio r1 shares with the base
        # station, the operator's identity is answered and r1's is refused (denied on ingress).
        base_ip = ip_address_of(f"{PREFIX}{run_id}-laptop")
        r1_ns, to_base = f"{PREFIX}{run_id}-r1", f"quic/{base_ip}:{PORT}"
        assert ask_operator_key(r1_ns, to_base, fleet / "operator", "operator", team, env) >= 1, \
            "the operator identity got no answer over QUIC (the positive control)"
        assert ask_operator_key(r1_ns, to_base, fleet / "r1", "r1", team, env) == 0, \
            "a robot's identity was answered on the operator key over QUIC"

        # the chains deliver over QUIC: every sink takes in more outputs
        def sinks() -> dict:
            snap = json.loads(run_cli(["status", "--json", "--timeout", "3"], env).stdout)
            out = dict((snap.get("basestation") or {}).get("sinks") or {})
            for info in snap["robots"].values():
                out.update((info["status"] or {}).get("sinks") or {})
            return out

        first = wait_until(lambda: (s := sinks()) and len(s) == 5 and s, 20, "every chain's sink to report")
        wait_until(lambda: all(s["received_total"] >= first[c]["received_total"] + 5 for c, s in sinks().items()),
                   30, "every sink to take in 5 more outputs")

        snap = json.loads(run_cli(["status", "--json"], env).stdout)
        before = len(snap["faults"])
        result = run_cli(["fault", "cut", "r1", "laptop", "--json"], env)
        assert result.returncode == 0, result.stderr
        t_cut = json.loads(result.stdout)["fault"]["t_unix"]

        def handled():
            s = json.loads(run_cli(["status", "--json", "--timeout", "3"], env).stdout)
            return next((f for f in s["faults"][before:] if f["kind"] == "link-down" and f["target"] == "laptop-r1"
                         and f["detected_unix"] >= t_cut and f["reconfigured_unix"]), None)

        fault = wait_until(handled, 20, "the cut to be detected and handled")
        print(f"testbed cut over QUIC: detected {fault['detected_unix'] - t_cut:.3f} s, "
              f"reconfigured {fault['reconfigured_unix'] - t_cut:.3f} s")
        # the TLS testbed's bounds (test_testbed.py), with the same 0.5 s lease
        assert fault["detected_unix"] - t_cut <= 1.0
        assert fault["reconfigured_unix"] - t_cut <= 1.5
        assert json.loads(run_cli(["status", "--json"], env).stdout)["robots"]["r1"]["present"]  # via a relay
        assert run_cli(["fault", "heal", "r1", "laptop"], env).returncode == 0
        wait_until(lambda: not json.loads(run_cli(["status", "--json"], env).stdout)["links_down"], 20,
                   "the link back")
        # after the heal every chain goes on, and what the cut held up arrived, once (a summary after
        # Ctrl-C is the one at ready: it cannot say this)
        healed = sinks()
        settled = wait_until(lambda: (s := sinks()) and all(
            s[c]["received_total"] >= healed[c]["received_total"] + 5 and s[c]["contiguous"] == s[c]["max_seq"] + 1
            for c in healed) and s, 30, "every sink to take in 5 more outputs, without a gap, after the heal")
        for chain, sink in settled.items():
            assert sink["duplicates_total"] == 0, (chain, sink)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-2000:]
    finally:
        stop(proc)  # after a failed assertion too, so it cleans up
    assert not {n for n in ours() if n.startswith(f"{PREFIX}{run_id}-")}, "Ctrl-C left namespaces behind"
