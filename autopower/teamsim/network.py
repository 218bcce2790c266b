"""The simulated radio network of a team: its links, what each direction of a link does to a
message, and the sessions (Zenoh's) whose leases say who sees whom.

Rules:

- The links are the scenario's (its topology, each link on its first medium choice). A message
  crosses one link, in one direction; a direction sends one message at a time, each taking the
  airtime of its size at the rate in force while it is on air, then the link's latency (plus a
  jitter drawn from ``[0, jitter_s]``, which reorders messages), unless the direction loses it
  (``loss``, drawn) or is cut. A duplicated message (``dup``, drawn) arrives twice. A change of
  rate (`set_rate`) re-times what is queued or on air: a backlog built while a link was slow
  drains at its rate once it is restored, as a radio's queue does.
- A message is sent only on a session (the pair is connected); it arrives only if the session
  still holds, the direction is not cut and the receiving process is the one it was sent to.
- A pair is healthy when both processes are up and not frozen and neither direction is cut. A
  pair unhealthy for a whole lease disconnects: both ends lose each other's tokens. A pair healthy
  for a reconnect delay connects again: both see each other's tokens. A process that ends
  disconnects its pairs at once (its peers see the connection close).
- Every draw comes from the one ``random.Random`` given, in the order of the events.
"""

from __future__ import annotations

import random
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

from autopower.errors import ProtocolError
from autopower.model.network import build_network
from autopower.model.scenario import Scenario
from autopower.protocol import Packet, Relayed, decode
from autopower.protocol.codec import message_kind
from autopower.teamsim.scheduler import Scheduler

LATENCY_S = 0.002  # one way, per link
LEASE_S = 1.0  # Zenoh's lease (`ZenohSettings.lease_ms`)
RECONNECT_S = 0.5  # a healed link's session is back after this (Zenoh's retry period, at most 0.5 s)
DUPLICATE_GAP_S = 0.0005  # a duplicate arrives this long after the original


class Endpoint(Protocol):
    """What the network hands messages and sight changes to (a node's `SimBus`)."""

    frozen: bool

    def subscribes(self, key: str) -> bool: ...

    def arrive(self, sender: str, key: str, payload: bytes) -> None: ...

    def sight(self, peer: str, alive: bool) -> None: ...


@dataclass
class OnAir:
    """A message queued or on air in one direction, until its last bit is sent (`SimNetwork.set_rate`)."""

    start: float  # when its airtime begins
    end: float  # when its last bit is sent
    bits: float  # what it sends from ``start``
    latency_s: float  # after its last bit, the link's latency
    jitter_s: float  # ... and its jitter (drawn when it was sent)
    dup: bool  # it arrives twice
    arrival: tuple  # `SimNetwork._arrive`'s arguments
    live: list = field(default_factory=lambda: [True])  # False once re-timed: its scheduled arrival does nothing


@dataclass
class Direction:
    """One direction of a link: its rate and what faults do to it now."""

    kbps: float
    latency_s: float = LATENCY_S
    busy_until: float = 0.0
    cut: bool = False
    loss: float = 0.0
    dup: float = 0.0
    jitter_s: float = 0.0
    on_air: deque = field(default_factory=deque)  # `OnAir`s whose last bit is not sent yet, in order

    def sent_by(self, now: float) -> None:
        """Forget what has left this direction by ``now`` (its arrival is scheduled for good)."""
        while self.on_air and self.on_air[0].end <= now:
            self.on_air.popleft()


@dataclass
class Pair:
    """The session between two nodes (both directions of their link)."""

    connected: bool = False
    healthy: bool = False
    version: int = 0  # bumped at every change of health: a scheduled check of an older one does nothing


@dataclass
class NetStats:
    sent: int = 0
    delivered: int = 0
    unsent: int = 0  # no session: nothing left the sender
    cut: int = 0
    lost: int = 0
    duplicated: int = 0
    # what was sent (a session carried it away), by message kind: [messages, bytes]. A relayed or
    # routed message counts once per hop, as a radio carries it once per hop.
    by_kind: dict[str, list[int]] = field(default_factory=dict)


class SimNetwork:
    def __init__(self, scenario: Scenario, scheduler: Scheduler, rng: random.Random, *,
                 lease_s: float = LEASE_S, reconnect_s: float = RECONNECT_S):
        self.scheduler = scheduler
        self.rng = rng
        self.lease_s = lease_s
        self.reconnect_s = reconnect_s
        self.nodes = tuple(scenario.node_names())
        self.directions: dict[tuple[str, str], Direction] = {}
        peers: dict[str, list[str]] = {n: [] for n in self.nodes}
        for link in build_network(scenario).links:
            kbps = scenario.radios[link.medium].kbps
            for a, b in ((link.a, link.b), (link.b, link.a)):
                self.directions[(a, b)] = Direction(kbps=kbps)
                peers[a].append(b)
        self.neighbours: dict[str, tuple[str, ...]] = {n: tuple(sorted(p)) for n, p in peers.items()}
        self.pairs: dict[frozenset[str], Pair] = {frozenset(d): Pair() for d in self.directions}
        self.endpoints: dict[str, Endpoint] = {}
        # (sender, key) -> (the subscriptions' version it was found at, the neighbours that subscribe)
        self._fanout: dict[tuple[str, str], tuple[int, tuple[str, ...]]] = {}
        self._subscriptions = 0  # bumped whenever a process comes, goes or (un)subscribes
        self.stats = NetStats()
        # second copies that reached their receiver, per (receiver, key): the evidence a sink's count
        # of duplicated outputs is checked against (`World.final_checks`)
        self.copies_arrived: dict[tuple[str, str], int] = {}
        # A routed packet's copy made on one hop reaches its end through the nodes that forward it,
        # each of which passes on both: the bodies of the packets a link duplicated, and how often
        # each node passed one on (its second time is the network's copy, not the team's: `transmit`)
        self._copied_bodies: set[bytes] = set()
        self._passed_on: dict[tuple[str, bytes], int] = {}
        # (sender, payload) -> the arrivals scheduled and not yet come: what is on its way (`in_transit`)
        self._transit: dict[tuple[str, bytes], int] = {}

    # ---- processes ---------------------------------------------------------------------------
    def attach(self, node: str, endpoint: Endpoint) -> None:
        """``node``'s process is up (its sessions connect after the reconnect delay)."""
        self.endpoints[node] = endpoint
        self.subscriptions_changed()
        self._reevaluate(node)

    def detach(self, node: str) -> None:
        """``node``'s process ended: its peers see its sessions close now."""
        self.endpoints.pop(node, None)
        self.subscriptions_changed()
        for peer in self.neighbours[node]:
            pair = self.pairs[frozenset((node, peer))]
            pair.healthy, pair.version = False, pair.version + 1
            if pair.connected:
                self._disconnect(node, peer)

    def subscriptions_changed(self) -> None:
        self._subscriptions += 1

    def subscribers(self, sender: str, key: str) -> tuple[str, ...]:
        """The neighbours of ``sender`` whose process subscribes to ``key``, in `neighbours` order
        (the order messages leave in). Found once per (sender, key) until a subscription changes:
        a key the base station addresses to one robot is not asked of each of its n neighbours at
        every status."""
        found = self._fanout.get((sender, key))
        if found is None or found[0] != self._subscriptions:
            endpoints = self.endpoints
            found = self._fanout[(sender, key)] = (self._subscriptions, tuple(
                peer for peer in self.neighbours[sender]
                if (far := endpoints.get(peer)) is not None and far.subscribes(key)))
        return found[1]

    def frozen_changed(self, node: str) -> None:
        self._reevaluate(node)

    def connected(self, a: str, b: str) -> bool:
        pair = self.pairs.get(frozenset((a, b)))
        return pair is not None and pair.connected

    # ---- faults ----------------------------------------------------------------------------------
    def direction(self, a: str, b: str) -> Direction | None:
        return self.directions.get((a, b))

    def set_cut(self, a: str, b: str, cut: bool) -> None:
        d = self.directions.get((a, b))
        if d is not None and d.cut != cut:
            d.cut = cut
            self._check(a, b)

    # ---- sessions -----------------------------------------------------------------------------------
    def _healthy(self, a: str, b: str) -> bool:
        ea, eb = self.endpoints.get(a), self.endpoints.get(b)
        return (ea is not None and eb is not None and not ea.frozen and not eb.frozen
                and not self.directions[(a, b)].cut and not self.directions[(b, a)].cut)

    def _reevaluate(self, node: str) -> None:
        for peer in self.neighbours[node]:
            self._check(node, peer)

    def _check(self, a: str, b: str) -> None:
        pair = self.pairs[frozenset((a, b))]
        healthy = self._healthy(a, b)
        if healthy == pair.healthy:
            return
        pair.healthy, pair.version = healthy, pair.version + 1
        wait = self.reconnect_s if healthy else self.lease_s
        self.scheduler.after(wait, self._settle, a, b, pair.version)

    def _settle(self, a: str, b: str, version: int) -> None:
        pair = self.pairs[frozenset((a, b))]
        if version != pair.version or pair.healthy == pair.connected:
            return
        if pair.healthy:
            pair.connected = True
            for me, peer in sorted(((a, b), (b, a))):
                self.endpoints[me].sight(peer, True)
        else:
            self._disconnect(a, b)

    def _disconnect(self, a: str, b: str) -> None:
        self.pairs[frozenset((a, b))].connected = False
        for me, peer in sorted(((a, b), (b, a))):
            endpoint = self.endpoints.get(me)
            if endpoint is not None:
                endpoint.sight(peer, False)

    # ---- messages ------------------------------------------------------------------------------------
    def transmit(self, sender: str, receiver: str, key: str, payload: bytes) -> None:
        """Send one message over the link ``sender`` -> ``receiver`` (see the module's rules)."""
        if not self.connected(sender, receiver):
            self.stats.unsent += 1
            return
        d = self.directions[(sender, receiver)]
        self.stats.sent += 1
        kind = message_kind(payload)
        counts = self.stats.by_kind.setdefault(_counted_kind(kind, payload), [0, 0])
        counts[0] += 1
        counts[1] += len(payload)
        carries_copy = kind in _CARRIERS and bool(self._copied_bodies) and self._passes_on_a_copy(sender, payload)
        if d.cut:
            self.stats.cut += 1
            return
        if d.loss and self.rng.random() < d.loss:
            self.stats.lost += 1
            return
        now = self.scheduler.now
        d.sent_by(now)
        bits = len(payload) * 8
        start = max(now, d.busy_until)
        d.busy_until = start + bits / (d.kbps * 1000.0)
        jitter_s = self.rng.uniform(0.0, d.jitter_s) if d.jitter_s else 0.0
        air = OnAir(start, d.busy_until, bits, d.latency_s, jitter_s, False,
                    (sender, receiver, key, payload, self.endpoints[receiver], carries_copy))
        if d.dup and self.rng.random() < d.dup:
            self.stats.duplicated += 1
            if kind in _CARRIERS and (body := _body(payload)) is not None:
                self._copied_bodies.add(body)
            air.dup = True
        d.on_air.append(air)
        key_ = (sender, payload)
        self._transit[key_] = self._transit.get(key_, 0) + (2 if air.dup else 1)
        self._schedule(air)

    def _schedule(self, air: OnAir) -> None:
        arrival = air.end + air.latency_s + air.jitter_s
        self.scheduler.at(arrival, self._arrive_live, air.live, *air.arrival)
        if air.dup:
            self.scheduler.at(arrival + DUPLICATE_GAP_S, self._arrive_live, air.live, *air.arrival[:5], True)

    def set_rate(self, sender: str, receiver: str, kbps: float) -> None:
        """The direction's rate from now on: what it has queued or on air is sent at it."""
        d = self.directions[(sender, receiver)]
        if kbps == d.kbps:
            return
        now = self.scheduler.now
        d.sent_by(now)
        t = now
        for air in d.on_air:
            if air.start < now:  # on air: what is left of it
                air.bits *= (air.end - now) / (air.end - air.start)
                air.start = now
            else:  # queued behind the others (its start was the end of the one before)
                air.start = t
            air.end = air.start + air.bits / (kbps * 1000.0)
            t = air.end
            air.live[0] = False  # its arrival at the old time does nothing
            air.live = [True]
            self._schedule(air)
        d.busy_until = t if d.on_air else d.busy_until
        d.kbps = kbps

    def _passes_on_a_copy(self, sender: str, payload: bytes) -> bool:
        """``sender`` passes on a packet (or a relayed message) whose body a link duplicated before, for
        the second time (or later): what it forwards is that copy. (A body resent by its producer is a
        new attempt, other bytes: only a forwarder passes the same body on twice.)"""
        body = _body(payload)
        if body is None or body not in self._copied_bodies:
            return False
        times = self._passed_on[(sender, body)] = self._passed_on.get((sender, body), 0) + 1
        return times > 1

    def _arrive_live(self, live: list, *arrival) -> None:
        if live[0]:
            key = (arrival[0], arrival[3])
            left = self._transit.get(key, 0) - 1
            if left > 0:
                self._transit[key] = left
            else:
                self._transit.pop(key, None)
            self._arrive(*arrival)

    def in_transit(self, *, sender: str | None = None, but: str | None = None) -> list[bytes]:
        """The messages on their way now, from ``sender`` only or from any sender but ``but`` (a
        sender that dies takes what it has on the wire with it: its sessions close before it arrives)."""
        return [payload for (frm, payload) in self._transit
                if (sender is None or frm == sender) and (but is None or frm != but)]

    def _arrive(self, sender: str, receiver: str, key: str, payload: bytes, target: Endpoint,
                copy: bool = False) -> None:
        if self.endpoints.get(receiver) is not target or not self.connected(sender, receiver):
            self.stats.cut += 1
            return
        if self.directions[(sender, receiver)].cut:
            self.stats.cut += 1
            return
        self.stats.delivered += 1
        if copy:
            self.copies_arrived[(receiver, key)] = self.copies_arrived.get((receiver, key), 0) + 1
        target.arrive(sender, key, payload)


_CARRIERS = frozenset({"packet", "relayed"})  # what a forwarder passes on with its body unchanged


def _body(payload: bytes) -> bytes | None:
    """What a packet carries to its end, or a relayed message to its destination (None: garbled)."""
    try:
        msg = decode(payload, (Packet, Relayed))
    except ProtocolError:
        return None
    return msg.body if isinstance(msg, Packet) else msg.payload


def _counted_kind(kind: str | None, payload: bytes) -> str:
    """The kind a message is counted under: a relayed one as ``relayed:<what it carries>`` (a relay
    carries chain data as well as the control plane: `SimResult.traffic` splits them by it)."""
    if kind != "relayed":
        return kind or "other"
    body = _body(payload)
    return f"relayed:{(message_kind(body) if body is not None else None) or 'other'}"
