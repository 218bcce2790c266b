"""`autopower deploy init` and a fleet started from its output, as a user does it (subprocesses).

The fleet here is four hosts that all happen to be 127.0.0.1 (distinct ports): the same files a
robot gets, started with `--fleet DIR`, talking mutual TLS with default-deny access control.
"""

from __future__ import annotations

import json
import os
import stat
import subprocess
import time
from pathlib import Path

import pytest

from autopower.launch.localhost import free_ports
from tests.e2e.test_up import AUTOPOWER, env_for, run_cli

pytestmark = pytest.mark.slow
NODES = ("laptop", "r1", "r2", "r3")


def write_fleet(path: Path, ports: dict[str, int], team: str = "lab") -> Path:
    lines = [f'team = "{team}"', "lease_ms = 1000"]
    for node, port in ports.items():
        lines += [f"[nodes.{node}]", 'address = "127.0.0.1"', f"port = {port}"]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture
def fleet_out(tmp_path):
    ports = dict(zip(NODES, free_ports(len(NODES)), strict=True))
    fleet = write_fleet(tmp_path / "fleet.toml", ports, team=f"lab{os.getpid()}")
    out = tmp_path / "out"
    result = run_cli(["deploy", "init", "paper-fig7", "--fleet", str(fleet), "--out", str(out)], env_for(tmp_path))
    assert result.returncode == 0, result.stderr
    return out, result


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_deploy_init_writes_keys_0600_and_never_prints_them(fleet_out):
    out, result = fleet_out
    assert mode(out) == 0o700 and mode(out / "ca") == 0o700
    assert mode(out / "ca" / "ca.key") == 0o600
    for node in (*NODES, "operator"):
        d = out / node
        assert mode(d) == 0o700
        assert mode(d / f"{node}.key") == 0o600
        assert not (d / "ca.key").exists(), "the CA key must not be in a node's directory"
    printed = result.stdout + result.stderr
    assert "PRIVATE KEY" not in printed
    for key in out.rglob("*.key"):
        body = "".join(key.read_text().splitlines()[1:-1])
        assert body[:40] not in printed


def test_each_certificate_names_its_node_and_address(fleet_out):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    out, _ = fleet_out
    ca = x509.load_pem_x509_certificate((out / "ca" / "ca.pem").read_bytes())
    for node in NODES:
        cert = x509.load_pem_x509_certificate((out / node / f"{node}.pem").read_bytes())
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == node
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert "127.0.0.1" in [str(ip) for ip in san.get_values_for_type(x509.IPAddress)]
        cert.verify_directly_issued_by(ca)


def test_each_node_config_is_mtls_scouting_off_default_deny_with_a_lease(fleet_out):
    out, _ = fleet_out
    for node in NODES:
        info = json.loads((out / node / "node.json").read_text())
        text = (out / node / "zenoh.json5").read_text()
        config = json.loads("\n".join(l for l in text.splitlines() if not l.startswith("//")))
        assert config["transport"]["link"]["tls"]["enable_mtls"] is True
        assert config["transport"]["link"]["tls"]["listen_private_key"] == f"/etc/autopower/{node}.key"
        assert config["scouting"]["multicast"]["enabled"] is False and config["scouting"]["gossip"]["enabled"] is False
        assert config["transport"]["link"]["tx"]["lease"] == 1000
        assert config["access_control"]["enabled"] and config["access_control"]["default_permission"] == "deny"
        assert all(ep.startswith("tls/") for ep in info["zenoh"]["listen"] + info["zenoh"]["connect"])
        unit = (out / node / f"autopower-{node}.service").read_text()
        assert f"--fleet /etc/autopower --node {node}" in unit
    # paper-fig7 is fully connected: every pair of the four nodes has exactly one connection
    connects = sum(len(json.loads((out / n / "node.json").read_text())["zenoh"]["connect"]) for n in NODES)
    assert connects == 6


def test_a_bad_fleet_is_one_line_and_exit_2(tmp_path):
    fleet = tmp_path / "fleet.toml"
    fleet.write_text('team = "lab"\n[nodes.laptop]\nport = 7447\n')
    result = run_cli(["deploy", "init", "paper-fig7", "--fleet", str(fleet), "--out", str(tmp_path / "o")],
                     env_for(tmp_path))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "nodes.laptop: missing address" in result.stderr
    fleet.write_text('team = "lab"\n[nodes.laptop]\naddress = "127.0.0.1"\n')
    result = run_cli(["deploy", "init", "paper-fig7", "--fleet", str(fleet), "--out", str(tmp_path / "o")],
                     env_for(tmp_path))
    assert result.returncode == 2 and "no host for r1, r2, r3" in result.stderr


def test_a_fleet_started_from_its_directories_runs_and_answers_the_operator(fleet_out, tmp_path):
    out, _ = fleet_out
    env = env_for(tmp_path)
    procs = []
    try:
        procs.append(subprocess.Popen([AUTOPOWER, "basestation", "--fleet", str(out), "--node", "laptop",
                                       "--speed", "5", "--log-level", "warning"], env=env,
                                      stdout=subprocess.DEVNULL, stderr=open(tmp_path / "laptop.log", "wb")))
        for robot in ("r1", "r2", "r3"):  # a node's own directory, as installed on the robot
            procs.append(subprocess.Popen([AUTOPOWER, "agent", "--fleet", str(out / robot), "--log-level", "warning"],
                                          env=env, stdout=subprocess.DEVNULL,
                                          stderr=open(tmp_path / f"{robot}.log", "wb")))
        deadline, snap = time.monotonic() + 90, {}
        while time.monotonic() < deadline:
            assert all(p.poll() is None for p in procs), [p.poll() for p in procs]
            result = run_cli(["status", "--fleet", str(out / "operator"), "--json", "--timeout", "3"], env)
            if result.returncode == 0:
                snap = json.loads(result.stdout)
                if snap.get("ready"):
                    break
            time.sleep(0.5)
        assert snap.get("ready"), f"the fleet was not ready: {snap.get('events')}"
        assert all(info["present"] for info in snap["robots"].values())
        # operator commands take the operator's directory; a robot's is named as the mistake it is
        # (a robot identity that does query is refused by the ACL: tests/integration/test_security.py)
        wrong = run_cli(["status", "--fleet", str(out / "r1"), "--json", "--timeout", "2"], env)
        assert wrong.returncode == 2 and "node 'r1''s directory, not 'operator'" in wrong.stderr
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


def test_up_insecure_says_so_on_start_and_keeps_stdout_one_object(tmp_path):
    result = run_cli(["up", "--insecure", "--duration", "1", "--json", "--log-dir", str(tmp_path / "logs")],
                     env_for(tmp_path), timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "warning: --insecure: no TLS and no access control" in result.stderr
    assert "relayed messages and subgroup votes are not signed" in result.stderr
    for name in ("laptop", "r1", "r2", "r3"):  # and every process says it in its log
        assert "are not signed" in (tmp_path / "logs" / f"{name}.log").read_text(), name
    json.loads(result.stdout)  # the warning went to stderr: stdout is still one JSON object
    assert not (tmp_path / "state" / "tls").exists() or not any((tmp_path / "state" / "tls").iterdir())


def test_up_by_default_generates_certificates_and_removes_them_at_the_end(tmp_path):
    result = run_cli(["up", "--duration", "1", "--json", "--log-dir", str(tmp_path / "logs")],
                     env_for(tmp_path), timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "--insecure" not in result.stderr
    logs = " ".join(p.read_text() for p in (tmp_path / "logs").glob("*.log"))
    assert "PRIVATE KEY" not in logs and "PRIVATE KEY" not in result.stdout + result.stderr
    tls = tmp_path / "state" / "tls"
    assert tls.is_dir() and mode(tls) == 0o700 and not any(tls.iterdir()), "the team's keys outlived it"
