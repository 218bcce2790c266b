"""What the base station believes about each link of the topology: facts, debounced.

Evidence comes from liveliness (the base station's own links) and from the robots' statuses
(who sees whom). Turning it into "down" and "back" is bookkeeping, not a decision (deciding
what to do about it is the policy's job), and it is where flapping is stopped:

- a link is *down* at once when an end that saw it up reports it down (its lease expired: that
  is the detection), but only after ``down_after_s`` of reports if it was never seen up (start-up)
  or if one of its ends has just come back (a thawed robot's sessions are still reconnecting);
- a link that was down is *back* once it has been seen up for its hold without a break:
  ``heal_hold_s``, doubled for each time it went down lately beyond the first (route-flap
  dampening, as BGP's: each down adds 1 to the link's penalty, which halves every
  ``flap_half_life_s``; the hold is ``heal_hold_s`` x 2^(penalty - 1), at most ``max_hold_s``).
  Every plan that uses a link and every plan that routes around it costs the team a
  reconfiguration, and a migration's state crosses the radio: a link flapping every 2 s would
  make one each way per cycle. Dampened, its second down holds it out for 4 s, its third 8 s,
  and so on, while a link that failed once in a while is back after ``heal_hold_s``.

An end's report that a down link is up counts only once that end has reported it down: the two
ends of a cut notice it at different times (each by its own lease; in a one-way cut the deaf end
first), and the statuses the later one sends meanwhile still say "up". Taken as the link back,
they made its own "down" that follows count as a flap, and a link cut once was held out for
3.3 s instead of ``heal_hold_s`` (issue 31 item 3). The same at the heal: once a down link is
seen up again, an end's report that it is down counts (as the link going down again) only once
that end has reported it up in this spell; before, the later end's last "down" ended the spell
and doubled the hold. The base station's own evidence (`seen`, `lost`) always counts.
"""

from __future__ import annotations

from typing import Iterable, Mapping

Pair = frozenset[str]

FLAP_HALF_LIFE_S = 60.0  # a link's flap penalty halves in this long (wall seconds)
MAX_HOLD_S = 120.0  # however much it flapped, a link up this long without a break is back


def pair_name(pair: Pair) -> str:
    return "-".join(sorted(pair))


class LinkStates:
    def __init__(self, pairs: Iterable[Pair], *, down_after_s: float, heal_hold_s: float,
                 flap_half_life_s: float = FLAP_HALF_LIFE_S, max_hold_s: float = MAX_HOLD_S):
        self.pairs = set(pairs)  # the topology's links: reports about other pairs are ignored
        self.down_after_s = down_after_s
        self.heal_hold_s = heal_hold_s
        self.flap_half_life_s = flap_half_life_s
        self.max_hold_s = max(max_hold_s, heal_hold_s)
        self._penalty: dict[Pair, tuple[float, float]] = {}  # pair -> (flap penalty, when it was that)
        self.down: set[Pair] = set()
        self._reported_down: dict[Pair, float] = {}  # pair -> first report of it down (this spell)
        self._seen_up: set[Pair] = set()
        self._up_since: dict[Pair, float] = {}  # down pairs seen up again -> since when
        self._rejoined: dict[str, float] = {}  # node -> when it came back
        self._caught_up: dict[Pair, set[str]] = {}  # down pair -> its ends that reported it down since
        self._back_from: dict[Pair, set[str]] = {}  # down pair seen up again -> its ends that reported it up

    def seen(self, a: str, b: str, now: float) -> None:
        """Evidence that a link works (its ends see each other)."""
        pair = frozenset((a, b))
        self._seen_up.add(pair)
        self._reported_down.pop(pair, None)
        if pair in self.down and pair not in self._up_since:
            self._up_since[pair] = now
            self._back_from[pair] = set()

    def lost(self, a: str, b: str, now: float) -> bool:
        """An end saw the link go (its own liveliness); True if it was not known down yet."""
        pair = frozenset((a, b))
        self._interrupted(pair, now)
        if pair in self.down:
            return False
        self._went_down(pair, now)
        return True

    def _went_down(self, pair: Pair, now: float) -> None:
        self.down.add(pair)
        self._caught_up[pair] = set()
        self._penalty[pair] = (self.flap_penalty(pair, now) + 1.0, now)

    def _interrupted(self, pair: Pair, now: float) -> None:
        """Evidence that ``pair`` is down: a down link whose up spell this ends flapped again."""
        self._back_from.pop(pair, None)
        if self._up_since.pop(pair, None) is not None and pair in self.down:
            self._penalty[pair] = (self.flap_penalty(pair, now) + 1.0, now)

    def flap_penalty(self, pair: Pair, now: float) -> float:
        """How often ``pair`` went down lately: +1 a time, halving every ``flap_half_life_s``."""
        value, at = self._penalty.get(pair, (0.0, now))
        return value * 0.5 ** (max(0.0, now - at) / self.flap_half_life_s)

    def hold_s(self, pair: Pair, now: float) -> float:
        """How long ``pair`` must be seen up without a break to be back (see the module's rule)."""
        penalty = self.flap_penalty(pair, now)
        return min(self.max_hold_s, self.heal_hold_s * 2.0 ** max(0.0, penalty - 1.0))

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
                if pair not in self.down or node in self._caught_up.get(pair, ()):  # see the module's docstring
                    self.seen(node, peer, now)
                    if pair in self._back_from:
                        self._back_from[pair].add(node)
                continue
            if pair in self._up_since and node not in self._back_from.get(pair, ()):
                continue  # made before this end saw the link back: no evidence (the module's docstring)
            if pair in self.down:
                self._caught_up.setdefault(pair, set()).add(node)
            if peer not in alive or node not in alive:  # a node gone is not a link down
                self._reported_down.pop(pair, None)
                continue
            self._interrupted(pair, now)
            since = self._reported_down.setdefault(pair, now)
            back = max(self._rejoined.get(node, -1.0), self._rejoined.get(peer, -1.0))
            settled = pair in self._seen_up and now - back >= self.down_after_s
            wait = 0.0 if settled else self.down_after_s
            if now - since >= wait and pair not in self.down:
                self._went_down(pair, now)
                self._caught_up[pair].add(node)
                out.append((pair, since))
        return out

    def healed(self, now: float) -> list[Pair]:
        """Pairs back up for their hold (`hold_s`): no longer down."""
        back = [p for p, since in self._up_since.items() if p in self.down and now - since >= self.hold_s(p, now)]
        for pair in back:
            self.down.discard(pair)
            self._up_since.pop(pair, None)
            self._back_from.pop(pair, None)
        return back
