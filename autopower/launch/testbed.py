"""A team on the testbed: each process in its node's network namespace, over shaped veth links.

`TestbedTeam` is a `LocalTeam` whose network is a `NamespaceNetwork`: the team's fleet is
generated the way `autopower deploy init` writes one for real hosts (a CA for this run, mutual
TLS on every link, over TCP or QUIC as ``spec.transport`` says, default-deny access control,
each node connecting to its neighbours' link addresses), each child starts inside its namespace
from its node directory (``--fleet``), and a fault cut silences the real link (random loss and
a one-way cut drop one direction's packets; a rate change re-shapes it; a flap or a roam cuts it
on a schedule the fault controller keeps).
Everything it created is removed when it stops, however it stops; `autopower testbed down`
removes what a killed run left.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import socket
import subprocess
import sys
import time

from autopower.basestation.operator import TLS_DIR, state_dir
from autopower.deploy.bundle import write_bundle
from autopower.deploy.fleet import Fleet, FleetNode
from autopower.deploy.pki import identity_in
from autopower.errors import AutoPowerError
from autopower.launch.localhost import PARENT_PID, Child, LocalTeam, TeamSpec, _die_with_parent, check_transport
from autopower.launch.netns import NamespaceNetwork, require_root
from autopower.model.network import build_network
from autopower.model.scenario import Scenario
from autopower.protocol.access import OPERATOR
from autopower.runtime.bus import ZenohSettings

log = logging.getLogger(__name__)

PORT = 7447  # every node listens on it in its own namespace


class _LinkSwitch:
    """What the fault controller cuts and heals (the same face as a `LinkProxy`)."""

    def __init__(self, net: NamespaceNetwork, a: str, b: str):
        self.net, self.a, self.b = net, a, b

    @property
    def is_cut(self) -> bool:
        return frozenset((self.a, self.b)) in self.net.cut_links

    @property
    def state(self) -> str:  # for `fault list`: up, cut, or what each direction drops
        return self.net.link_state(self.a, self.b)

    @property
    def drops(self) -> dict:
        """(sender, receiver) -> `Drop` on this link's directions."""
        return {pair: d for pair, d in self.net.drops.items() if set(pair) == {self.a, self.b}}

    def drop(self, src: str, dst: str, pct: float, *, kind: str) -> None:
        self.net.drop(src, dst, pct, kind=kind)

    @property
    def rate(self) -> float | None:
        """The rate (kbit/s, before the speed-up) `fault rate` gave this link; None: its medium's."""
        return self.net.rates.get(frozenset((self.a, self.b)))

    def set_rate(self, kbps: float) -> None:
        self.net.set_rate(self.a, self.b, kbps)

    def cut(self) -> None:
        self.net.cut(self.a, self.b)

    def uncut(self) -> None:  # the both-way cut only (a flap's up phase): drops and rate stay
        self.net.uncut(self.a, self.b)

    def heal(self) -> None:
        self.net.heal(self.a, self.b)

    def start(self) -> None:  # the link exists from `NamespaceNetwork.create` on
        pass

    def close(self) -> None:  # removed with the namespaces
        pass


class TestbedTeam(LocalTeam):
    """A team of processes in network namespaces (a context manager, like `LocalTeam`)."""

    __test__ = False  # not a pytest class

    def __init__(self, spec: TeamSpec, scenario: Scenario, *, shaping: bool = True):
        require_root()
        # the loopback parts of LocalTeam (ports, proxies, identities) are not used here
        super().__init__(dataclasses.replace(spec, secure=False, proxied_links=False, transport="tls"), scenario)
        self.spec = spec
        check_transport(dataclasses.replace(spec, secure=True, proxied_links=False))  # always TLS, real links
        media = dict(item.split("=", 1) for item in spec.media)
        network = build_network(scenario, topology=spec.topology, media=media or None)
        self.net = NamespaceNetwork(network, scenario.radios, speed=spec.speed, state_dir=state_dir(),
                                    shaping=shaping)
        self.proxies = {frozenset((l.a, l.b)): _LinkSwitch(self.net, l.a, l.b) for l in self.net.links}
        self.fleet_dir = state_dir() / TLS_DIR / self.team
        self.scheme = spec.transport
        self._bridge_sock: socket.socket | None = None
        self._bridge: subprocess.Popen | None = None
        self.network_s: float | None = None  # how long `start` took to build the namespaces and links

    # ---- what differs from localhost ------------------------------------------------------------------
    def fleet(self) -> Fleet:
        net = self.net
        nodes = {n: FleetNode(name=n, address=(net.addresses(n) or ["127.0.0.1"])[0], port=PORT,
                              listen_host="0.0.0.0") for n in self.nodes}
        via = {}
        for link in net.links:
            via[(link.a, link.b)] = link.address(link.b)
            via[(link.b, link.a)] = link.address(link.a)
        return Fleet(team=self.team, nodes=nodes, lease_ms=self.spec.lease_ms, via=via, transport=self.spec.transport)

    @property
    def base_endpoint(self) -> str:
        # the bridge forwards TCP: the operator reaches the base station over TLS whatever the team's
        # links run (the base station listens on both, `deploy.fleet.node_settings`)
        return f"tls/127.0.0.1:{self._bridge_sock.getsockname()[1]}"

    def operator_settings(self) -> ZenohSettings:
        return ZenohSettings(connect=(self.base_endpoint,), tls=identity_in(self.fleet_dir / OPERATOR, OPERATOR))

    def session_security(self) -> dict:
        files = identity_in(self.fleet_dir / OPERATOR, OPERATOR)
        return {"operator_tls": {"ca": files.ca, "cert": files.cert, "key": files.key},
                "testbed": self.net.run_id}

    def _common(self, node: str) -> list[str]:
        args = ["--fleet", str(self.fleet_dir / node), "--status-period", str(self.spec.status_period_s),
                "--heartbeat", str(self.spec.heartbeat_s),
                "--parent-pid", PARENT_PID, "--log-level", self.spec.log_level]
        if self.spec.record_dir is not None:
            args += ["--record-dir", str(self.spec.record_dir)]
        return args

    def _command(self, name: str, args: list[str]) -> list[str]:
        # a new interpreter (no fork server) starts in its namespace this way
        return [*self.net.exec_prefix(name), *super()._command(name, args)]

    def _netns(self, name: str) -> str | None:
        # forked from the fork server (in ours), a child joins its node's namespace before its first socket
        return self.net.ns(name)

    # ---- lifecycle ----------------------------------------------------------------------------------------
    def start(self) -> None:
        started = time.monotonic()
        self.net.create()
        # the emulator's own start (namespaces, veth pairs, shaping): what real robots do not run
        self.network_s = time.monotonic() - started
        base = self.scenario.basestation
        write_bundle(self.fleet_dir, self.spec.scenario, self.fleet(), topology=self.spec.topology,
                     addresses={base: ["127.0.0.1"]})  # the operator's bridge arrives on the base's loopback
        self._bridge_sock = socket.create_server(("127.0.0.1", 0))
        log_path = self.log_dir / "operator-bridge.log"
        with open(log_path, "wb") as out:
            fd = self._bridge_sock.fileno()
            self._bridge = subprocess.Popen(
                [*self.net.exec_prefix(base), sys.executable, "-m", "autopower.launch.nsbridge", str(fd), str(PORT)],
                pass_fds=(fd,), stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                process_group=0, preexec_fn=_die_with_parent)
        self.children["operator-bridge"] = Child("operator-bridge", self._bridge, log_path)
        self.expected_exits.add("operator-bridge")
        super().start()

    def stop(self, timeout_s: float = 8.0) -> dict[str, int | None]:
        try:
            codes = super().stop(timeout_s)
            if self._bridge is not None and self._bridge.poll() is None:
                self._bridge.terminate()
                try:
                    self._bridge.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    self._bridge.kill()
            return codes
        finally:
            if self._bridge_sock is not None:
                self._bridge_sock.close()
            self.net.destroy()
            shutil.rmtree(self.fleet_dir, ignore_errors=True)

    def check_children(self):
        if self._bridge is not None and self._bridge.poll() is not None:
            raise AutoPowerError(f"the operator bridge into {self.scenario.basestation}'s namespace exited "
                                 f"({self._bridge.returncode}); see {self.log_dir / 'operator-bridge.log'}")
        return super().check_children()  # supervised like on localhost: a crashed child restarts in its namespace
