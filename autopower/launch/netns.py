"""A scenario's network as Linux network namespaces: one per node, one veth pair per link, shaped.

Each node gets its own network stack (``ip netns``); each link of the scenario's topology is a
veth pair created directly inside the two nodes' namespaces (nothing is ever added to the host's
own namespace), addressed 10.99.<link>.1/.2, and shaped on both ends with a token bucket (tbf) to
the medium's rate × the speed-up, so a virtual second carries what the radio carries in a real
one (this kernel has no netem: no added delay or random loss). A cut swaps a link's qdisc for a
zero-length pfifo on both ends: every packet is dropped silently, no FIN, no RST, the interfaces
stay up, exactly a radio out of range; heal restores the shaping.

Every name starts with `PREFIX` and this run's id, and the run writes what it creates into
``<state dir>/testbed/<run>.json`` *before* creating it: `cleanup_stale` (`autopower testbed
down`) removes exactly what a killed run left and never a namespace it did not make.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import subprocess
from dataclasses import dataclass
from pathlib import Path

from autopower.errors import AutoPowerError
from autopower.model.network import Network

log = logging.getLogger(__name__)

PREFIX = "aptb-"  # AutoPower testbed: the only namespaces this module ever deletes
SUBNET = "10.99"


def require_root() -> None:
    if os.geteuid() != 0:
        raise AutoPowerError("the testbed needs root (it creates network namespaces and shapes links); "
                             "run it with sudo, or use `autopower up` for the localhost mode")


def _run(*cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True)
    if check and result.returncode != 0:
        raise AutoPowerError(f"`{' '.join(cmd)}` failed: {result.stderr.strip() or result.returncode}")
    return result


@dataclass(frozen=True)
class NetLink:
    index: int
    a: str
    b: str
    medium: str
    kbps: float  # the radio's real rate
    dev_a: str  # the interface in a's namespace
    dev_b: str

    def address(self, node: str) -> str:
        return f"{SUBNET}.{self.index}.{1 if node == self.a else 2}"


def _dev(index: int, peer: str) -> str:
    return f"l{index}-{peer}"[:15]  # unique inside one namespace; IFNAMSIZ is 16 with the NUL


def state_root(state_dir: Path) -> Path:
    return Path(state_dir) / "testbed"


class NamespaceNetwork:
    """The namespaces and shaped links of one run (a context manager: leaving removes them all)."""

    def __init__(self, network: Network, radios: dict, *, speed: float, state_dir: Path, shaping: bool = True,
                 run_id: str | None = None):
        self.run_id = run_id or secrets.token_hex(3)
        self.speed = speed
        self.shaping = shaping
        self.nodes = list(network.nodes)
        self.links = [NetLink(index=i + 1, a=l.a, b=l.b, medium=l.medium, kbps=radios[l.medium].kbps,
                              dev_a=_dev(i + 1, l.b), dev_b=_dev(i + 1, l.a))
                      for i, l in enumerate(network.links)]
        if len(self.links) > 250:
            raise AutoPowerError(f"{len(self.links)} links: the testbed addresses at most 250")
        self.state_file = state_root(state_dir) / f"{self.run_id}.json"
        self.cut_links: set[frozenset[str]] = set()
        self.created = False

    def ns(self, node: str) -> str:
        return f"{PREFIX}{self.run_id}-{node}"

    def link(self, a: str, b: str) -> NetLink:
        for link in self.links:
            if {link.a, link.b} == {a, b}:
                return link
        raise AutoPowerError(f"no link {a}-{b} in this testbed; links: "
                             f"{', '.join(f'{l.a}-{l.b}' for l in self.links) or 'none'}")

    def peer_address(self, node: str, peer: str) -> str:
        """The address ``node`` reaches ``peer`` at (the peer's end of their link)."""
        return self.link(node, peer).address(peer)

    def addresses(self, node: str) -> list[str]:
        return [l.address(node) for l in self.links if node in (l.a, l.b)]

    def rate_kbit(self, link: NetLink) -> int:
        return max(8, int(round(link.kbps * self.speed)))

    # ---- lifecycle -------------------------------------------------------------------------------
    def __enter__(self) -> "NamespaceNetwork":
        self.create()
        return self

    def __exit__(self, *exc) -> None:
        self.destroy()

    def create(self) -> None:
        require_root()
        self.state_file.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        # written first: a crash half-way leaves a record `testbed down` can clean from
        self.state_file.write_text(json.dumps({"pid": os.getpid(), "namespaces": [self.ns(n) for n in self.nodes]}))
        self.created = True
        try:
            for node in self.nodes:
                _run("ip", "netns", "add", self.ns(node))
                _run("ip", "-n", self.ns(node), "link", "set", "dev", "lo", "up")
            for link in self.links:
                na, nb = self.ns(link.a), self.ns(link.b)
                _run("ip", "link", "add", "name", link.dev_a, "netns", na, "type", "veth",
                     "peer", "name", link.dev_b, "netns", nb)
                for ns, dev, node in ((na, link.dev_a, link.a), (nb, link.dev_b, link.b)):
                    _run("ip", "-n", ns, "addr", "add", f"{link.address(node)}/24", "dev", dev)
                    _run("ip", "-n", ns, "link", "set", "dev", dev, "up")
                self._shape(link)
        except BaseException:
            self.destroy()
            raise
        log.info("testbed %s: %d namespaces, %d links", self.run_id, len(self.nodes), len(self.links))

    def _ends(self, link: NetLink):
        return ((self.ns(link.a), link.dev_a), (self.ns(link.b), link.dev_b))

    def _shape(self, link: NetLink) -> None:
        for ns, dev in self._ends(link):
            if self.shaping:
                rate = self.rate_kbit(link)
                burst = max(3200, rate * 1000 // 8 // 100)  # 10 ms of traffic, at least two frames
                _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate", f"{rate}kbit",
                     "burst", str(burst), "latency", "100ms")
            else:
                _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "pfifo", "limit", "1000")

    def cut(self, a: str, b: str) -> None:
        """Drop every packet on link a-b from now on, silently (both directions)."""
        link = self.link(a, b)
        for ns, dev in self._ends(link):
            _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "pfifo", "limit", "0")
        self.cut_links.add(frozenset((a, b)))

    def heal(self, a: str, b: str) -> None:
        link = self.link(a, b)
        self._shape(link)
        self.cut_links.discard(frozenset((a, b)))

    def destroy(self) -> None:
        if not self.created:
            return
        remove_namespaces(json.loads(self.state_file.read_text())["namespaces"])
        self.state_file.unlink(missing_ok=True)
        self.created = False

    def exec_prefix(self, node: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns(node)]


def remove_namespaces(names) -> list[str]:
    """Delete these namespaces (and with them their veth ends); only names with our prefix."""
    existing = set(list_namespaces())
    removed = []
    for name in names:
        if name.startswith(PREFIX) and name in existing:
            _run("ip", "netns", "del", name, check=False)
            removed.append(name)
    return removed


def list_namespaces() -> list[str]:
    result = _run("ip", "netns", "list", check=False)
    return [line.split()[0] for line in result.stdout.splitlines() if line.strip()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except (ProcessLookupError, OSError):
        return False


def cleanup_stale(state_dir: Path) -> list[str]:
    """Remove what testbed runs that are no longer alive left behind; return the namespaces removed."""
    require_root()
    removed = []
    for record in sorted(state_root(state_dir).glob("*.json")):
        try:
            info = json.loads(record.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if _alive(int(info.get("pid", 0))):
            continue  # a running testbed cleans up after itself
        removed += remove_namespaces(info.get("namespaces", []))
        record.unlink(missing_ok=True)
    return removed
