"""`autopower deploy init`: one directory per node with everything that node needs, and nothing more.

Layout of OUT (copy ``OUT/<node>/`` to ``/etc/autopower`` on that host; keep ``OUT/ca/`` on the
operator's machine, never on a robot)::

    OUT/ca/ca.pem, ca.key          the team CA (ca.key 0600: it can make new identities)
    OUT/<node>/node.json           team, scenario, role, Zenoh settings (what `--fleet` reads)
    OUT/<node>/zenoh.json5         the same settings as a Zenoh configuration file
    OUT/<node>/ca.pem, <node>.pem  the CA and the node's certificate (CN = node, SAN = addresses)
    OUT/<node>/<node>.key          the node's private key (0600)
    OUT/<node>/autopower-<node>.service   a systemd unit (robots and the base station)
    OUT/operator/...               the operator CLI's identity and client settings

A node's directory is self-contained and relocatable: paths in ``node.json`` are relative to it.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from autopower.deploy.fleet import Fleet, node_settings, operator_settings
from autopower.deploy.pki import CA_CERT, TeamCA
from autopower.errors import AutoPowerError
from autopower.model.loading import load_scenario, resolve_scenario_path
from autopower.model.scenario import Scenario
from autopower.protocol.access import OPERATOR
from autopower.runtime.bus import TlsFiles, ZenohSettings

NODE_FILE = "node.json"
SCENARIO_COPY = "scenario.toml"
DEFAULT_INSTALL_DIR = "/etc/autopower"
DEFAULT_EXEC = "/opt/autopower/.venv/bin/autopower"


@dataclass(frozen=True)
class NodeBundle:
    """What `--fleet DIR --node NAME` starts from."""

    directory: Path
    team: str
    node: str
    role: str  # "basestation" | "robot" | "operator"
    scenario: str  # a built-in name or a path (resolved inside the directory)
    zenoh: ZenohSettings


def _tls(directory: Path, node: str, relative: bool) -> TlsFiles:
    base = Path() if relative else directory
    return TlsFiles(ca=str(base / CA_CERT), cert=str(base / f"{node}.pem"), key=str(base / f"{node}.key"))


def _settings_json(settings: ZenohSettings) -> dict:
    return {"mode": settings.mode, "listen": list(settings.listen), "connect": list(settings.connect),
            "lease_ms": settings.lease_ms, "access_control": settings.access_control,
            "shared_memory": settings.shared_memory}


def write_bundle(out: Path, scenario_name: str, fleet: Fleet, *, topology: str | None = None,
                 install_dir: str = DEFAULT_INSTALL_DIR, exec_path: str = DEFAULT_EXEC,
                 addresses: dict[str, list[str]] | None = None) -> dict[str, Path]:
    """Write the CA and every node's directory into ``out``; return node -> directory.

    ``addresses`` adds SANs beyond what the fleet lists (e.g. 127.0.0.1 for localhost runs).
    """
    scenario = load_scenario(scenario_name)
    fleet.check_covers(scenario)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    os.chmod(out, 0o700)
    where, text = resolve_scenario_path(scenario_name)
    builtin = where.startswith("<built-in")
    ca = TeamCA.create(out / "ca", fleet.team)
    written: dict[str, Path] = {}
    roles = {scenario.basestation: "basestation", **{r.name: "robot" for r in scenario.robots}, OPERATOR: "operator"}
    for node, role in roles.items():
        directory = out / node
        if directory.exists():
            shutil.rmtree(directory)  # stale keys of a previous init must not survive next to new ones
        sans = (fleet.addresses_of(node) if node in fleet.nodes else []) + list((addresses or {}).get(node, []))
        ca.issue(node, sans, directory)
        os.chmod(directory, 0o700)
        if role == "operator":
            settings = operator_settings(fleet, scenario, _tls(directory, node, relative=True))
        else:
            settings = node_settings(fleet, scenario, node, _tls(directory, node, relative=True), topology=topology)
        if not builtin:
            (directory / SCENARIO_COPY).write_text(text, encoding="utf-8")
        info = {"team": fleet.team, "node": node, "role": role,
                "scenario": scenario_name if builtin else SCENARIO_COPY, "zenoh": _settings_json(settings)}
        (directory / NODE_FILE).write_text(json.dumps(info, indent=2) + "\n")
        installed = ZenohSettings(**{**settings.__dict__, "tls": _tls(Path(install_dir), node, relative=False)})
        (directory / "zenoh.json5").write_text(
            f"// Zenoh configuration of AutoPower {role} {node!r}, team {fleet.team!r} (autopower deploy init).\n"
            f"// Paths assume this directory is installed at {install_dir}.\n"
            + json.dumps(installed.to_dict(), indent=2) + "\n")
        if role != "operator":
            unit = resources.files("autopower.deploy").joinpath("templates/node.service").read_text()
            command = "basestation" if role == "basestation" else "agent"
            (directory / f"autopower-{node}.service").write_text(unit.format(
                role="base station" if role == "basestation" else "robot", node=node, team=fleet.team,
                install_dir=install_dir, exec=exec_path, command=command))
        written[node] = directory
    return written


def load_bundle(fleet_dir: Path, node: str | None = None) -> NodeBundle:
    """The node directory ``fleet_dir/node`` (or ``fleet_dir`` itself when it is one)."""
    fleet_dir = Path(fleet_dir)
    directory = fleet_dir / node if node and (fleet_dir / node / NODE_FILE).is_file() else fleet_dir
    path = directory / NODE_FILE
    try:
        info = json.loads(path.read_text())
    except FileNotFoundError:
        hint = f" --node {node}" if node else " --node NAME"
        raise AutoPowerError(f"{path} is missing: --fleet takes the directory `autopower deploy init` wrote "
                             f"(with{hint}) or one node's copy of it") from None
    except json.JSONDecodeError as exc:
        raise AutoPowerError(f"{path} is corrupt ({exc}); run `autopower deploy init` again") from None
    if node and info.get("node") != node:
        raise AutoPowerError(f"{directory} is node {info.get('node')!r}'s directory, not {node!r}")
    z = info["zenoh"]
    scenario = info["scenario"]
    if scenario == SCENARIO_COPY:
        scenario = str(directory / SCENARIO_COPY)
    settings = ZenohSettings(mode=z["mode"], listen=tuple(z["listen"]), connect=tuple(z["connect"]),
                             lease_ms=int(z["lease_ms"]), access_control=z["access_control"],
                             shared_memory=z.get("shared_memory"),
                             tls=_tls(directory.resolve(), info["node"], relative=False))
    return NodeBundle(directory=directory, team=info["team"], node=info["node"], role=info["role"],
                      scenario=scenario, zenoh=settings)


def scenario_of(bundle: NodeBundle) -> Scenario:
    return load_scenario(bundle.scenario)
