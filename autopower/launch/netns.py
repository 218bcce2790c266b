"""A scenario's network as Linux network namespaces: one per node, a veth pair or a bridge per medium, shaped.

Each node gets its own network stack (``ip netns``). A medium that only two nodes use is a veth
pair created directly inside the two nodes' namespaces (nothing is ever added to the host's own
namespace), addressed 10.99.<link>.1/.2, and shaped on both ends with a token bucket (tbf) to the
medium's rate × the speed-up, so a virtual second carries what the radio carries in a real one
(this kernel has no netem: no added delay; random loss comes from nftables, below). A cut swaps
the link's qdisc for a zero-length pfifo on both ends: every packet is dropped silently, no FIN,
no RST, the interfaces stay up, exactly a radio out of range; heal restores the shaping.

A broadcast medium — three or more nodes whose radios of that medium all reach each other (the
fully-connected topology over one radio) — is one radio per node on a shared channel, as the
energy model counts it (a node's radio is busy with the sum of what it sends and receives over
all its links of that medium): a Linux bridge in a namespace of its own (a `Segment`), one veth
per node attached to it, addressed 10.98.<segment>.<n>, shaped per node — the node's end to the
rate (what it sends), the bridge's end towards it to the rate (what it receives) — so every link
of that node shares its radio's capacity. A cut link gets a blackhole route for the other's
address in both namespaces: packets are dropped before they leave, silently for the peer (no
FIN, no RST, nothing on the wire); a new connection attempt fails at once (EINVAL) rather than
timing out. A cut of one link leaves the node's other links on that medium working. A star (GSM
to the base station only) stays one shaped veth pair per link: its hub's radio is not shared.

A direction of a link can lose packets too (`drop`): random loss (a share of them) or a one-way
cut (all of them). The receiving node's namespace gets an nftables table of the testbed's own
(`NFT_TABLE`) whose input rules match the link's interface and the sender's address and drop a
random share with ``numgen random`` (no netem, no tc filters needed). The packets cross the link
and use its rate as a lost radio frame does, and the sender is not told. Heal removes them.

A point-to-point link's rate can change while it runs (`set_rate`: a robot moving away): both
ends are shaped again with tbf to the new rate × the speed-up; a cut link keeps its cut and gets
the new rate when it comes back (`uncut`). Heal restores the medium's rate. A shared medium has
no qdisc per link (each node's radio is shaped, and this kernel has no tc filters to tell its
links apart), so it refuses a rate change.

Every name starts with `PREFIX` and this run's id, and the run writes what it creates into
``<state dir>/testbed/<run>.json`` *before* creating it: `cleanup_stale` (`autopower testbed
down`) removes exactly what a killed run left and never a namespace it did not make.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from autopower.errors import AutoPowerError
from autopower.model.network import Network
from autopower.runtime.pids import pid_alive

log = logging.getLogger(__name__)

PREFIX = "aptb-"  # AutoPower testbed: the only namespaces this module ever deletes
# TCP gives up on a connection whose data stays unacknowledged for about 1.4 s (retransmissions
# modelled from the 200 ms minimum RTO) instead of the kernel's ~15 min (15). Why: Zenoh removes
# a peer's liveliness tokens only once it has closed the link after its lease, and the close waits
# for the link's writer; on a silently cut link carrying camera frames that writer is stuck in a
# write to a full socket buffer that never drains, so the peer stays "alive" until the link comes
# back and TCP's backed-off retransmission gets through. Every node of a real team needs the same
# setting (docs/deploying/robots.md).
TCP_RETRIES2 = 2
# A SYN every second for ten tries (the kernel's default: four at 1 s, then backed off to 2, 4 ...
# s). A cut closes a session and its connecting end retries at once; while the link stays down the
# attempt's SYNs are lost, and after the heal it waited for the next backed-off one: up to 3 s before
# the two ends saw each other again. Every node of a real team needs the same (docs/deploying/robots.md).
# A kernel without the setting (older ones) is left as it is.
TCP_SYN_LINEAR_TIMEOUTS = 10
SYN_LINEAR_SYSCTL = Path("/proc/sys/net/ipv4/tcp_syn_linear_timeouts")
SUBNET = "10.99"  # point-to-point links
SHARED_SUBNET = "10.98"  # shared media (bridges)
NFT_TABLE = "autopower"  # the nftables table (family ip) the testbed owns in each node's namespace
# a drop rule compares a random number below LOSS_SCALE with pct × LOSS_SCALE / 100: 0.01 % steps
LOSS_SCALE = 10000


def require_root() -> None:
    if os.geteuid() != 0:
        raise AutoPowerError("the testbed needs root (it creates network namespaces and shapes links); "
                             "run it with sudo, or use `autopower up` for the localhost mode")


def _run(*cmd: str, check: bool = True, stdin: str | None = None) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, capture_output=True, text=True, input=stdin)
    if check and result.returncode != 0:
        raise AutoPowerError(f"`{' '.join(cmd)}` failed: {result.stderr.strip() or result.returncode}")
    return result


@dataclass(frozen=True)
class Segment:
    """A shared medium: a bridge every node with a radio of that medium is attached to."""

    index: int
    medium: str
    kbps: float
    nodes: tuple[str, ...]

    def address(self, node: str) -> str:
        return f"{SHARED_SUBNET}.{self.index}.{self.nodes.index(node) + 1}"

    @property
    def dev(self) -> str:  # the node's interface on this medium (one per medium in a namespace)
        return f"m{self.index}"

    def port(self, node: str) -> str:  # the bridge's end towards the node
        return f"p{self.nodes.index(node) + 1}"


@dataclass(frozen=True)
class NetLink:
    index: int
    a: str
    b: str
    medium: str
    kbps: float  # the radio's real rate
    dev_a: str  # the interface in a's namespace
    dev_b: str
    segment: Segment | None = None  # set when the link crosses a shared medium's bridge

    def address(self, node: str) -> str:
        if self.segment is not None:
            return self.segment.address(node)
        return f"{SUBNET}.{self.index}.{1 if node == self.a else 2}"


@dataclass(frozen=True)
class Drop:
    """What one direction of a link drops: ``kind`` ``loss`` (a random share) or ``cut`` (all)."""

    kind: str
    pct: float

    def label(self) -> str:
        return "cut" if self.kind == "cut" else f"loss {self.pct:g}%"


def loss_steps(pct) -> int:
    """``pct`` (0 < pct <= 100) in the drop rule's 0.01 % steps; a clear error for anything else."""
    try:
        value = float(pct)
    except (TypeError, ValueError):
        value = float("nan")
    steps = round(value * LOSS_SCALE / 100) if value == value else 0
    if not (0 < value <= 100) or steps < 1:
        raise AutoPowerError(f"packet loss {pct!r} is not a percentage in (0, 100]; give e.g. 30 for 30 %, "
                             f"at least {100 / LOSS_SCALE:g}")
    return steps


def rate_kbps(kbps) -> float:
    """``kbps`` (a radio's rate in kbit/s, > 0) as a number; a clear error for anything else."""
    try:
        value = float(kbps)
    except (TypeError, ValueError):
        value = float("nan")
    if not (0 < value < float("inf")):
        raise AutoPowerError(f"link rate {kbps!r} is not a rate in kbit/s above 0; give e.g. 500 for 500 kbit/s "
                             "(the radio's rate; the testbed multiplies it by its --speed)")
    return value


def require_nft() -> None:
    if shutil.which("nft") is None:
        raise AutoPowerError("packet loss and one-way cuts on the testbed need nftables' `nft` tool, which is not "
                             "installed; install it (Debian/Ubuntu: apt-get install nftables)")


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
        self.segments: list[Segment] = []
        for medium in dict.fromkeys(l.medium for l in network.links):
            users = [n for n in self.nodes if any(l.medium == medium and l.touches(n) for l in network.links)]
            pairs = {frozenset((l.a, l.b)) for l in network.links if l.medium == medium}
            # a broadcast channel: three or more radios that all reach each other on it (a star,
            # such as GSM to the base station only, stays one shaped veth pair per link)
            if len(users) >= 3 and len(pairs) == len(users) * (len(users) - 1) // 2:
                self.segments.append(Segment(index=len(self.segments) + 1, medium=medium,
                                             kbps=radios[medium].kbps, nodes=tuple(users)))
        shared = {seg.medium: seg for seg in self.segments}
        self.links = []
        for i, l in enumerate(network.links):
            seg = shared.get(l.medium)
            self.links.append(NetLink(index=i + 1, a=l.a, b=l.b, medium=l.medium, kbps=radios[l.medium].kbps,
                                      dev_a=seg.dev if seg else _dev(i + 1, l.b),
                                      dev_b=seg.dev if seg else _dev(i + 1, l.a), segment=seg))
        if len(self.links) > 250 or len(self.segments) > 250 or len(self.nodes) > 250:
            raise AutoPowerError(f"{len(self.links)} links, {len(self.nodes)} nodes: the testbed addresses at most 250")
        self.state_file = state_root(state_dir) / f"{self.run_id}.json"
        self.cut_links: set[frozenset[str]] = set()
        # (sender, receiver) -> what is dropped on that direction of their link (see `drop`)
        self.drops: dict[tuple[str, str], Drop] = {}
        # link -> the rate (the radio's real kbit/s, before the speed-up) `set_rate` put in place of its medium's
        self.rates: dict[frozenset[str], float] = {}
        self.created = False

    def ns(self, node: str) -> str:
        return f"{PREFIX}{self.run_id}-{node}"

    def segment_ns(self, seg: Segment) -> str:
        return f"{PREFIX}{self.run_id}-medium{seg.index}"

    @property
    def namespaces(self) -> list[str]:
        """Every namespace of this run: one per node, one per shared medium's bridge."""
        return [self.ns(n) for n in self.nodes] + [self.segment_ns(seg) for seg in self.segments]

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
        return list(dict.fromkeys(l.address(node) for l in self.links if node in (l.a, l.b)))

    def describe(self) -> dict:
        """Each link's medium and shaped rate, and which nodes share a medium's bridge (for summaries)."""
        return {"links": {f"{l.a}-{l.b}": {"medium": l.medium, "kbit_s": self.rate_kbit(l),
                                           "shared": l.segment is not None} for l in self.links},
                "shared_media": {seg.medium: {"nodes": list(seg.nodes), "kbit_s_per_node": self.rate_kbit(seg)}
                                 for seg in self.segments}}

    def rate_kbit(self, link: NetLink | Segment) -> int:
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
        self.state_file.write_text(json.dumps({"pid": os.getpid(), "namespaces": self.namespaces}))
        self.created = True
        try:
            for node in self.nodes:
                _run("ip", "netns", "add", self.ns(node))
                _run("ip", "-n", self.ns(node), "link", "set", "dev", "lo", "up")
                _run("ip", "netns", "exec", self.ns(node), "sysctl", "-qw", f"net.ipv4.tcp_retries2={TCP_RETRIES2}")
                if SYN_LINEAR_SYSCTL.exists():
                    _run("ip", "netns", "exec", self.ns(node), "sysctl", "-qw",
                         f"net.ipv4.tcp_syn_linear_timeouts={TCP_SYN_LINEAR_TIMEOUTS}")
            for seg in self.segments:
                self._create_segment(seg)
            for link in self.links:
                if link.segment is not None:
                    continue
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

    def _create_segment(self, seg: Segment) -> None:
        """The bridge of a shared medium and each node's radio on it, shaped per node."""
        bridge_ns = self.segment_ns(seg)
        _run("ip", "netns", "add", bridge_ns)
        _run("ip", "-n", bridge_ns, "link", "add", "name", "br0", "type", "bridge")
        _run("ip", "-n", bridge_ns, "link", "set", "dev", "br0", "up")
        for node in seg.nodes:
            ns, port = self.ns(node), seg.port(node)
            _run("ip", "link", "add", "name", seg.dev, "netns", ns, "type", "veth", "peer", "name", port,
                 "netns", bridge_ns)
            _run("ip", "-n", bridge_ns, "link", "set", "dev", port, "master", "br0")
            _run("ip", "-n", bridge_ns, "link", "set", "dev", port, "up")
            _run("ip", "-n", ns, "addr", "add", f"{seg.address(node)}/24", "dev", seg.dev)
            _run("ip", "-n", ns, "link", "set", "dev", seg.dev, "up")
            # what the node sends (its end) and what it receives (the bridge's end towards it)
            for where, dev in ((ns, seg.dev), (bridge_ns, port)):
                self._qdisc(where, dev, seg.kbps)

    def _blackhole(self, a: str, b: str, *, add: bool) -> None:
        """Drop a's packets to b's address on their shared medium and b's to a's, before they leave."""
        seg = next(s for s in self.segments if a in s.nodes and b in s.nodes)
        for src, dst in ((a, b), (b, a)):
            _run("ip", "-n", self.ns(src), "route", "replace" if add else "del", "blackhole",
                 f"{seg.address(dst)}/32", check=add)

    def _ends(self, link: NetLink):
        return ((self.ns(link.a), link.dev_a), (self.ns(link.b), link.dev_b))

    def _qdisc(self, ns: str, dev: str, kbps: float) -> None:
        if self.shaping:
            rate = max(8, int(round(kbps * self.speed)))
            burst = max(3200, rate * 1000 // 8 // 100)  # 10 ms of traffic, at least two frames
            _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate", f"{rate}kbit",
                 "burst", str(burst), "latency", "100ms")
        else:
            _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "pfifo", "limit", "1000")

    def _shape(self, link: NetLink) -> None:
        kbps = self.rates.get(frozenset((link.a, link.b)), link.kbps)
        for ns, dev in self._ends(link):
            self._qdisc(ns, dev, kbps)

    def cut(self, a: str, b: str) -> None:
        """Drop every packet on link a-b from now on, silently (both directions)."""
        link = self.link(a, b)
        if link.segment is not None:  # the node's other links on that medium stay up
            self._blackhole(a, b, add=True)
        else:
            for ns, dev in self._ends(link):
                _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", "pfifo", "limit", "0")
        self.cut_links.add(frozenset((a, b)))

    def uncut(self, a: str, b: str) -> None:
        """Remove the both-way cut of link a-b only: its drops and its changed rate stay."""
        link = self.link(a, b)
        if link.segment is not None:
            self._blackhole(a, b, add=False)
        else:
            self._shape(link)
        self.cut_links.discard(frozenset((a, b)))

    def heal(self, a: str, b: str) -> None:
        """Bring link a-b back: both-way cut and every drop in either direction removed, the medium's rate."""
        self.rates.pop(frozenset((a, b)), None)  # first: uncut shapes the link to the medium's rate
        self.uncut(a, b)
        self.clear_drops(a, b)

    # ---- a changed rate (tbf on both ends of a veth pair) -----------------------------------------
    def set_rate(self, a: str, b: str, kbps) -> None:
        """Shape link a-b, both ways, to ``kbps`` (the radio's real rate) × the speed-up from now on.

        A cut link stays cut (a zero-length queue, not a tbf) and gets the rate when it comes back.
        """
        link = self.link(a, b)
        value = rate_kbps(kbps)
        if link.segment is not None:
            raise AutoPowerError(f"link {a}-{b} crosses the shared {link.medium} medium, whose rate is each node's "
                                 "radio, not the link's: a rate change needs a point-to-point link (start the "
                                 "testbed with e.g. `--media laptop-robot=gsm`)")
        if not self.shaping:
            raise AutoPowerError("this testbed runs with --no-shaping: its links have no rate to change; "
                                 "start it without --no-shaping")
        key = frozenset((a, b))
        before = self.rates.get(key)
        self.rates[key] = value
        if key in self.cut_links:
            return
        try:
            self._shape(link)
        except AutoPowerError:  # not applied: the state must keep saying what the namespaces hold
            if before is None:
                del self.rates[key]
            else:
                self.rates[key] = before
            raise

    # ---- per-direction drops (nftables in the receiver's namespace) -------------------------------
    def drop(self, src: str, dst: str, pct: float, *, kind: str = "loss") -> None:
        """Drop ``pct`` % of the packets ``src`` sends to ``dst`` over their link, at random (100: all).

        Replaces what was dropped on that direction before; the other direction is untouched.
        """
        self.link(src, dst)
        steps = loss_steps(pct)
        require_nft()
        before = self.drops.get((src, dst))
        self.drops[(src, dst)] = Drop(kind=kind, pct=steps * 100 / LOSS_SCALE)
        try:
            self._apply_drops(dst)
        except AutoPowerError:  # not applied: the state must keep saying what the namespace holds
            if before is None:
                del self.drops[(src, dst)]
            else:
                self.drops[(src, dst)] = before
            raise

    def clear_drops(self, a: str, b: str) -> None:
        """Remove the drops on both directions of link a-b (nothing to do when there are none)."""
        for src, dst in ((a, b), (b, a)):
            if self.drops.pop((src, dst), None) is not None:
                self._apply_drops(dst)

    def link_state(self, a: str, b: str) -> str:
        """``up``, ``cut``, a changed rate and what each direction drops, e.g.
        ``rate 500 kbps, cut r1->laptop, loss 30% laptop->r1``."""
        rate = self.rates.get(frozenset((a, b)))
        parts = [] if rate is None else [f"rate {rate:g} kbps"]
        if frozenset((a, b)) in self.cut_links:
            return ", ".join(["cut", *parts])
        parts += [f"{d.label()} {src}->{dst}" for (src, dst), d in sorted(self.drops.items())
                  if {src, dst} == {a, b}]
        return ", ".join(parts) or "up"

    def _drop_rule(self, src: str, dst: str, drop: Drop) -> str:
        """The nftables rule, in ``dst``'s namespace, that drops what ``src`` sends it over their link."""
        link = self.link(src, dst)
        dev = link.dev_b if dst == link.b else link.dev_a
        chance = "" if drop.pct >= 100 else f"numgen random mod {LOSS_SCALE} < {loss_steps(drop.pct)} "
        return f'iifname "{dev}" ip saddr {link.address(src)} {chance}drop comment "{drop.kind} {src}->{dst}"'

    def _apply_drops(self, node: str) -> None:
        """Make ``node``'s table hold exactly the drops towards it, atomically (one nft transaction).

        Declaring then deleting the table removes it whether or not it existed; the table is then
        written again only when something is to be dropped, so a healed node holds no rules at all.
        """
        rules = [self._drop_rule(src, dst, d) for (src, dst), d in sorted(self.drops.items()) if dst == node]
        script = [f"table ip {NFT_TABLE}", f"delete table ip {NFT_TABLE}"]
        if rules:
            script += [f"table ip {NFT_TABLE} {{", "  chain links {",
                       "    type filter hook input priority filter; policy accept;",
                       *(f"    {rule}" for rule in rules), "  }", "}"]
        _run("ip", "netns", "exec", self.ns(node), "nft", "-f", "-", stdin="\n".join(script) + "\n")

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


def cleanup_stale(state_dir: Path) -> list[str]:
    """Remove what testbed runs that are no longer alive left behind; return the namespaces removed."""
    require_root()
    removed = []
    for record in sorted(state_root(state_dir).glob("*.json")):
        try:
            info = json.loads(record.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        if pid_alive(int(info.get("pid", 0))):
            continue  # a running testbed cleans up after itself
        removed += remove_namespaces(info.get("namespaces", []))
        record.unlink(missing_ok=True)
    return removed
