"""The fleet: which host each node of a scenario runs on, and each node's Zenoh settings from it.

A fleet file (TOML) names the team and gives every node of the scenario an address (and
optionally a port, and the address others use to reach it over a given link)::

    team = "lab"
    lease_ms = 1000
    transport = "tls"         # or "quic"; default "tls"
    [nodes.laptop]            # the scenario's base station
    address = "192.168.50.1"
    [nodes.r1]
    address = "192.168.50.11"
    port = 7447               # default 7447

Links follow the scenario's topology: over each link the node later in the scenario's node
order connects to the earlier one, so every linked pair has exactly
one mutual-TLS session and unlinked pairs have none (the agents relay for them). ``transport``
says what carries the links between nodes: ``tls`` (TLS over TCP) or ``quic`` (Zenoh's QUIC link,
UDP on the same port number, the same certificates and access control; `runtime.bus.TRANSPORTS`).
The operator CLI reaches the base station over ``tls`` either way.
"""

from __future__ import annotations

import ipaddress
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from autopower.errors import AutoPowerError
from autopower.model.network import build_network
from autopower.model.scenario import Scenario
from autopower.protocol.access import OPERATOR, TeamAccess
from autopower.protocol.keys import Keys, check_name
from autopower.runtime.access_control import zenoh_access_control
from autopower.runtime.bus import TRANSPORTS, TlsFiles, ZenohSettings

DEFAULT_PORT = 7447


@dataclass(frozen=True)
class FleetNode:
    name: str
    address: str  # what the others connect to (the certificate's SAN)
    port: int = DEFAULT_PORT
    listen_host: str | None = None  # default: the address itself


@dataclass(frozen=True)
class Fleet:
    team: str
    nodes: dict[str, FleetNode]
    lease_ms: int = 1000
    # (node, peer) -> the address ``node`` uses to reach ``peer`` (a peer with one address per link)
    via: dict[tuple[str, str], str] = field(default_factory=dict)
    transport: str = "tls"  # what carries the links between nodes (one of TRANSPORTS)

    def __post_init__(self):
        if self.transport not in TRANSPORTS:
            raise AutoPowerError(f"transport {self.transport!r}: expected one of {', '.join(TRANSPORTS)}")

    def check_covers(self, scenario: Scenario) -> None:
        missing = [n for n in scenario.node_names() if n not in self.nodes]
        if missing:
            raise AutoPowerError(f"the fleet has no host for {', '.join(missing)} (scenario {scenario.name}); "
                                 f"add [nodes.{missing[0]}] address = \"...\" to the fleet file")

    def addresses_of(self, node: str) -> list[str]:
        """Every address others reach ``node`` at (the SANs of its certificate)."""
        out = [self.nodes[node].address]
        out += [addr for (_, peer), addr in self.via.items() if peer == node]
        return list(dict.fromkeys(out))

    def endpoint(self, node: str, peer: str, scheme: str | None = None) -> str:
        """Where ``node`` connects to reach ``peer`` (over the fleet's transport unless ``scheme``)."""
        host = self.via.get((node, peer), self.nodes[peer].address)
        return f"{scheme or self.transport}/{_host(host)}:{self.nodes[peer].port}"


def _host(address: str) -> str:
    try:
        return f"[{address}]" if ipaddress.ip_address(address).version == 6 else address
    except ValueError:
        return address


def load_fleet(path: Path) -> Fleet:
    """Read and check a fleet file; every problem is one line naming the file and the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise AutoPowerError(f"{path}: no such fleet file; see deploy/fleet.example.toml") from None
    except tomllib.TOMLDecodeError as exc:
        raise AutoPowerError(f"{path}: not valid TOML: {exc}") from None
    team = data.get("team")
    try:
        check_name(team, "team")
    except ValueError as exc:
        raise AutoPowerError(f"{path}: team: {exc}; expected e.g. team = \"lab\"") from None
    lease = data.get("lease_ms", 1000)
    if not isinstance(lease, int) or lease < 100:
        raise AutoPowerError(f"{path}: lease_ms = {lease!r}; expected an integer >= 100 (milliseconds)")
    transport = data.get("transport", "tls")
    if transport not in TRANSPORTS:
        raise AutoPowerError(f"{path}: transport = {transport!r}; expected one of "
                             f"{', '.join(repr(t) for t in TRANSPORTS)} (TLS over TCP, or Zenoh's QUIC link)")
    unknown = set(data) - {"team", "lease_ms", "transport", "nodes"}
    if unknown:
        raise AutoPowerError(f"{path}: unknown field(s) {', '.join(sorted(unknown))}; "
                             "expected team, lease_ms, transport, [nodes.NAME]")
    raw = data.get("nodes")
    if not isinstance(raw, dict) or not raw:
        raise AutoPowerError(f"{path}: no [nodes.NAME] tables; give each node of the scenario an address")
    nodes = {}
    for name, spec in raw.items():
        where = f"{path}: nodes.{name}"
        try:
            check_name(name, "node")
        except ValueError as exc:
            raise AutoPowerError(f"{where}: {exc}") from None
        if name == OPERATOR:
            raise AutoPowerError(f"{where}: {OPERATOR!r} is the operator CLI's identity; rename the node")
        if not isinstance(spec, dict) or not isinstance(spec.get("address"), str) or not spec["address"]:
            raise AutoPowerError(f"{where}: missing address; expected address = \"192.168.50.11\" (or a host name)")
        port = spec.get("port", DEFAULT_PORT)
        if not isinstance(port, int) or not 1 <= port <= 65535:
            raise AutoPowerError(f"{where}.port = {port!r}; expected a TCP port 1-65535")
        unknown = set(spec) - {"address", "port", "listen"}
        if unknown:
            raise AutoPowerError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}; "
                                 "expected address, port, listen")
        nodes[name] = FleetNode(name=name, address=spec["address"], port=port, listen_host=spec.get("listen"))
    return Fleet(team=team, nodes=nodes, lease_ms=lease, transport=transport)


def linked_pairs(scenario: Scenario, topology: str | None = None) -> list[tuple[str, str]]:
    """(connecting node, listening node) for each link of the scenario's topology."""
    order = scenario.node_names()
    rank = {n: i for i, n in enumerate(order)}
    pairs = []
    for link in build_network(scenario, topology=topology).links:
        early, late = sorted((link.a, link.b), key=rank.__getitem__)
        pairs.append((late, early))
    return sorted(pairs, key=lambda p: (rank[p[0]], rank[p[1]]))


def team_access(scenario: Scenario, team: str) -> TeamAccess:
    return TeamAccess(Keys(team), scenario.basestation, tuple(r.name for r in scenario.robots))


def node_settings(fleet: Fleet, scenario: Scenario, node: str, tls: TlsFiles, *,
                  topology: str | None = None, lease_ms: int | None = None) -> ZenohSettings:
    """One node's Zenoh settings: listen on its own address, connect along its links, mTLS, ACL."""
    me = fleet.nodes[node]
    at = f"{_host(me.listen_host or me.address)}:{me.port}"
    listen: tuple[str, ...] = (f"{fleet.transport}/{at}",)
    if node == scenario.basestation and fleet.transport != "tls":
        # The operator CLI connects over TLS whatever the team's links are: it opens one session
        # per command and asks and answers, so a stalled TCP stream costs it a slower answer,
        # never a link the team closes; and TCP passes where UDP may not (the testbed's bridge
        # from the host into the base station's namespace forwards TCP connections, a site's
        # firewall). TCP and UDP ports are apart: both listeners use the node's port.
        listen += (f"tls/{at}",)
    connect = tuple(fleet.endpoint(node, peer) for late, peer in linked_pairs(scenario, topology) if late == node)
    return ZenohSettings(listen=listen, connect=connect, lease_ms=lease_ms or fleet.lease_ms, tls=tls,
                         access_control=zenoh_access_control(team_access(scenario, fleet.team)),
                         shared_memory=False)  # separate hosts: every byte crosses the link


def operator_settings(fleet: Fleet, scenario: Scenario, tls: TlsFiles) -> ZenohSettings:
    """The operator CLI: connects to the base station only and listens on nothing."""
    base = scenario.basestation
    return ZenohSettings(connect=(fleet.endpoint(OPERATOR, base, scheme="tls"),), tls=tls,
                         lease_ms=fleet.lease_ms)
