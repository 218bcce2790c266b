"""What the base station believes about each link of the topology: facts, debounced.

Evidence comes from liveliness (the base station's own links) and from the robots' statuses
(who sees whom). Turning it into "down" and "back" is bookkeeping, not a decision (deciding
what to do about it is the policy's job), and it is where flapping is stopped:

- a link is *down* at once when an end that saw it up reports it down (its lease expired: that
  is the detection), but only after ``down_after_s`` of reports if it was never seen up (start-up)
  or if one of its ends has just come back (a thawed robot's sessions are still reconnecting);
- a link that was down is *back* once it has been seen up for ``heal_hold_s`` without a break.
"""

from __future__ import annotations

from typing import Iterable, Mapping

Pair = frozenset[str]


def pair_name(pair: Pair) -> str:
    return "-".join(sorted(pair))


class LinkStates:
    def __init__(self, pairs: Iterable[Pair], *, down_after_s: float, heal_hold_s: float):
        self.pairs = set(pairs)  # the topology's links: reports about other pairs are ignored
        self.down_after_s = down_after_s
        self.heal_hold_s = heal_hold_s
        self.down: set[Pair] = set()
        self._reported_down: dict[Pair, float] = {}  # pair -> first report of it down (this spell)
        self._seen_up: set[Pair] = set()
        self._up_since: dict[Pair, float] = {}  # down pairs seen up again -> since when
        self._rejoined: dict[str, float] = {}  # node -> when it came back

    def seen(self, a: str, b: str, now: float) -> None:
        """Evidence that a link works (its ends see each other)."""
        pair = frozenset((a, b))
        self._seen_up.add(pair)
        self._reported_down.pop(pair, None)
        if pair in self.down:
            self._up_since.setdefault(pair, now)

    def lost(self, a: str, b: str) -> bool:
        """An end saw the link go (its own liveliness); True if it was not known down yet."""
        pair = frozenset((a, b))
        self._up_since.pop(pair, None)
        if pair in self.down:
            return False
        self.down.add(pair)
        return True

    def rejoined(self, node: str, now: float) -> None:
        self._rejoined[node] = now

    def reported(self, node: str, links: Mapping[str, bool], alive: set[str], now: float) -> list[tuple[Pair, float]]:
        """A node's view of its links; returns the pairs now counted down, with when they went."""
        out = []
        for peer, up in links.items():
            pair = frozenset((node, peer))
            if pair not in self.pairs:
                continue
            if up:
                self.seen(node, peer, now)
                continue
            if peer not in alive or node not in alive:  # a node gone is not a link down
                self._reported_down.pop(pair, None)
                continue
            self._up_since.pop(pair, None)
            since = self._reported_down.setdefault(pair, now)
            back = max(self._rejoined.get(node, -1.0), self._rejoined.get(peer, -1.0))
            settled = pair in self._seen_up and now - back >= self.down_after_s
            wait = 0.0 if settled else self.down_after_s
            if now - since >= wait and pair not in self.down:
                self.down.add(pair)
                out.append((pair, since))
        return out

    def healed(self, now: float) -> list[Pair]:
        """Pairs back up for ``heal_hold_s``: no longer down."""
        back = [p for p, since in self._up_since.items() if p in self.down and now - since >= self.heal_hold_s]
        for pair in back:
            self.down.discard(pair)
            self._up_since.pop(pair, None)
        return back
