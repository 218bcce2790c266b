"""Relaying on arrival: a packet that only crosses this node is forwarded from the Zenoh callback.

A packet whose route goes on past this node needs nothing of the node's state but whether the
next node is in sight. Queued for the process's loop, it paid a thread switch and the loop's turn
on top of decoding and re-encoding it whole: one relay hop cost 1.7x (200 B) to 2.9x (230 KB) a
bare Zenoh echo (bench/bench_relay.py; 1.02-1.12x now). So the process's callback for its data key
offers each packet here first (`relay_now`), which

- reads its header without copying the body (`protocol.forwarding.read_header`: as strict as the
  codec; what it cannot judge goes to the codec on the loop),
- checks what `Frames.on_data` checks: the mission has started, this node is the hop the packet is
  addressed to, every medium is one of the scenario's radios; and that the next node is in direct
  sight (`NodePorts.in_sight`, the process's `Relayer` view), so it is published straight to it,
- publishes the next hop's copy: the header re-encoded with ``hop + 1``, the body bytes as they came.

Everything else goes to the loop exactly as before: the last hop (this node consumes the packet), a
next node out of sight (the loop's `Relayer` routes around it), before the mission, garbage.

The loop's state is never touched from here. Each forward is noted (its header and virtual time)
in a deque, and the loop charges them (`Metering.settle_relayed`, before every timer turn,
status and saved state): the radios' energy, receive on the incoming hop's medium and send on the outgoing one, as
`on_data` charges it, and the "forwarded" count; so the battery, the status and the recording see
the same energy as if the loop had forwarded each packet itself.

zenoh-python runs the callback on the subscription's own Python thread, fed by a bounded channel
(Zenoh's default FIFO): a put that blocks here stalls our data key's deliveries, and once that channel is full,
the transport's reception from the previous hop (its other messages, its keep-alives), which the
loop never did. So when a forward took longer than `CONGESTED_S` (the link to the next node is
backed up; a normal put takes microseconds) packets for that node go through the loop again for
`CONGESTED_HOLD_S`, where a blocked put holds the loop while the callback keeps filling the
loop's bounded queue, as before.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Callable, Mapping

from autopower.node.control_meter import ControlPlaneMeter
from autopower.node.meter import BatteryMeter
from autopower.protocol import Keys
from autopower.protocol.forwarding import PacketHeader, forwarded, read_header
from autopower.runtime.bus import Bus

CONGESTED_S = 0.05  # a forward's put that took this long: the next node's link is backed up
CONGESTED_HOLD_S = 1.0  # then its packets go through the loop for this long (wall seconds)
SETTLE_LIMIT = 100_000  # forwards not charged yet (the loop charges them every turn, at least every status period)


class ArrivalRelay:
    """Forwarding on the transport's thread (`relay_now`), charged on the loop (`settle`).

    It owns what was forwarded and not charged yet, which next nodes are backed up, and their data
    keys. It reads the node only through what it is given: whether the mission has started, its
    virtual time, who is in direct sight; ``monotonic`` times a put (wall seconds)."""

    def __init__(self, *, node: str, radios: Mapping[str, object], keys: Keys, bus: Bus,
                 in_sight: Callable[[str], bool], started: Callable[[], bool], now: Callable[[], float],
                 monotonic: Callable[[], float] = time.monotonic):
        self._node = node
        self._radios = radios
        self._keys = keys
        self._bus = bus
        self._in_sight = in_sight
        self._started = started
        self._now = now
        self._monotonic = monotonic
        # what was forwarded on arrival, for the loop to charge: (header, virtual time, slow put, bytes);
        # appended and taken one at a time (atomic), bounded: when full, packets go to the loop
        self._relayed: deque[tuple[PacketHeader, float, bool, int]] = deque()
        self._congested_until: dict[str, float] = {}  # next node -> monotonic time
        self._data_keys: dict[str, str] = {}  # next node -> its data key

    def relay_now(self, payload: bytes) -> bool:
        """Forward ``payload`` (a packet on our data key) now if it only crosses this node.

        Thread-safe; True if it was forwarded, False if the loop must handle it (`on_data`).
        """
        if not self._started() or len(self._relayed) >= SETTLE_LIMIT:
            return False
        header = read_header(payload)
        if header is None:
            return False
        path, hop = header.path, header.hop
        if hop >= len(path) - 1 or path[hop] != self._node:
            return False
        nxt = path[hop + 1]
        if not self._in_sight(nxt) or not self._known_media(header.media):
            return False
        if nxt in self._congested_until and self._congested_until[nxt] > self._monotonic():
            return False
        key = self._data_keys.get(nxt)
        if key is None:  # (the key's name check is not free: once per node)
            key = self._data_keys[nxt] = self._keys.node_data(nxt)
        started = self._monotonic()
        out = forwarded(payload, header)
        self._bus.publish(key, out)
        slow = self._monotonic() - started > CONGESTED_S
        if slow:
            self._congested_until[nxt] = self._monotonic() + CONGESTED_HOLD_S
        self._relayed.append((header, self._now(), slow, len(out)))
        return True

    def _known_media(self, media: tuple[str, ...]) -> bool:
        for medium in media:
            if medium not in self._radios:
                return False
        return True

    def settle(self, meter: BatteryMeter, control_plane: ControlPlaneMeter) -> tuple[int, int]:
        """On the loop: charge ``meter`` and ``control_plane`` for what was forwarded on arrival
        since last time; (packets, of them after a slow put)."""
        charges: dict[tuple[str, str, int, float, str, str], tuple[int, float]] = {}
        n = slow = 0
        while self._relayed:
            header, t, congested, size = self._relayed.popleft()
            n += 1
            slow += congested
            hop = header.hop
            control_plane.note_data(header.path[hop - 1], "receive", size)
            control_plane.note_data(header.path[hop + 1], "send", size)
            for direction, medium, peer in (("receive", header.media[hop - 1], header.path[hop - 1]),
                                            ("send", header.media[hop], header.path[hop + 1])):
                key = (direction, medium, header.charge_bytes, header.weight, header.purpose, peer)
                charges[key] = (charges.get(key, (0, t))[0] + 1, t)
        # one charge per kind for its n packets (the meter's charge is linear in the weight), at
        # the virtual time of the latest: what `on_data` charges packet by packet
        for (direction, medium, charge_bytes, weight, purpose, peer), (count, t) in charges.items():
            meter.charge_radio(direction, medium, charge_bytes, weight * count, t, purpose, peer=peer)
        return n, slow
