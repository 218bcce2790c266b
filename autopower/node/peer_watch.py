"""Who a robot sees directly: the transport's liveliness tokens, checked by the statuses that arrive.

A peer is in direct sight while its liveliness token is (the transport's lease: a session that
died is gone within it) *and* its statuses keep arriving directly. A token alone is not enough: a
link that fails in one direction, or a peer whose loop is stuck, keeps its session (and token)
while nothing it says arrives. So a peer whose direct statuses stay away for ``periods`` of the
status period it announced (ours if it announced none) counts as silent, out of sight, never
sooner than the lease and one period (`runtime.cadence.silence_limit_s`: a peer's loop may wait a
lease in a put to a link of its own that died, and a team configured with a long lease, for
radios that stay saturated for seconds, must not have its peers declared gone by this detector
first). Its next direct status brings it back.

On a link that loses statuses the silence allowed grows with the loss it shows (an accrual
detector, as phi-accrual adapts to the heartbeats it observes): each status that arrives tells how
many before it went missing (the gap over the announced period), a decaying count of those gives
the link's loss rate p, and a peer is declared silent only after m statuses in a row went missing,
the least m for which the expected false suspicions, (statuses a day) · p^m for each watched peer,
stay within ``false_suspicions_per_day`` for the robot. On a clean link m is 1 and ``periods``
rule, as before; at 10 % loss m is 7, at 20 % 9 or 10, and never more than ``max_periods``. A cut
(both ways or one way) ends the transport's session, and the lease, not this detector, finds it:
what this detector adds is a peer whose loop is stuck while its session lives, found later on a
lossy link than on a clean one, and that is the trade.

`PeerWatch` owns that state and nothing else. Time comes in with each call; what changed goes out
as return values, for the process to act on (tell its runtime, its relayer, its subgroup rounds).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from autopower.runtime.cadence import next_silence_s, silence_limit_s, status_period_s

DAY_S = 86_400.0


@dataclass(frozen=True)
class WatchSettings:
    periods: float = 2.0  # announced status periods a peer may stay silent
    own_period_s: float = 0.5  # our status period: a peer that announced none is judged by it
    lease_s: float = 0.5  # the transport's lease: never sooner than this
    false_suspicions_per_day: float = 1.0  # a robot's budget of false suspicions on lossy links
    max_periods: float = 12.0  # however lossy the link, silent this many periods is silent
    loss_memory: float = 500.0  # statuses the loss estimate remembers (it decays by 1/this a status)
    clean_prior: float = 20.0  # statuses without loss the estimate starts from (one loss is not 100 %)


class PeerWatch:
    def __init__(self, settings: WatchSettings):
        self.settings = settings
        self.tokens: set[str] = set()  # nodes whose liveliness token we see
        self.silent: set[str] = set()  # nodes with a token but no direct status for too long
        self._heard: dict[str, float] = {}  # node -> wall time of its last status received directly
        self._announced: dict[str, float] = {}  # node -> the status period it said it keeps
        self.suspicions = 0  # peers declared silent (each later heard again was a false suspicion)
        self.tokens_lost = 0  # peers whose token going took them out of sight (the lease, or a closed session)
        self._missed: dict[str, float] = {}  # node -> statuses seen missing (decaying count)
        self._expected: dict[str, float] = {}  # node -> statuses it sent (arrived + missing, decaying)
        # `limits` and `next_deadline`, kept until something they depend on changes: a loop asks for
        # both at every turn, and a fleet's robot watches dozens of peers
        self._limits: dict[str, float] | None = None
        self._deadline: tuple[float | None] | None = None

    def _changed(self, limits: bool = False) -> None:
        self._deadline = None
        if limits:
            self._limits = None

    def on_token(self, node: str, alive: bool) -> bool | None:
        """``node``'s token came or went; the change of sight to act on (None: none)."""
        self._changed(limits=True)
        if alive:
            self.tokens.add(node)
            self.silent.discard(node)
            self._heard.pop(node, None)  # back: silence counts from its next status
            return True
        self.tokens.discard(node)
        if node in self.silent:  # already out of sight (silent): nothing changes
            self.silent.discard(node)
            return None
        self.tokens_lost += 1
        return False

    def on_status(self, node: str, next_status_s: float, now: float) -> bool:
        """A status of ``node`` arrived directly (not relayed); True: it is back in sight (was silent)."""
        self._count_missing(node, now)
        self._announced[node] = next_status_s
        self._heard[node] = now
        if node in self.silent and node in self.tokens:
            self.silent.discard(node)
            self._changed(limits=True)
            return True
        self._changed()
        if self._limits is not None and node in self._limits:  # its own limit only: one status, one peer
            self._limits[node] = self._limit(node)
        return False

    def heard_at(self, node: str) -> float | None:
        """The wall time ``node``'s last direct status was taken (None: none since its token came)."""
        return self._heard.get(node)

    def _period_s(self, node: str) -> float:
        """The status period ``node`` announced (ours if it announced none)."""
        return status_period_s(self.settings.own_period_s, self._announced.get(node, 0.0))

    def _count_missing(self, node: str, now: float) -> None:
        """Before a direct status of ``node`` is taken: how many went missing since the last one.

        A status says the next comes within its period: a gap of k periods is k - 1 missing. A gap
        that made the peer silent counts no more than its limit allowed, and one after its token
        came back (never heard since) counts nothing: an outage is not the link's loss rate.
        """
        heard = self._heard.get(node)
        if heard is None:
            return
        period = self._period_s(node)
        missing = max(0, round((now - heard) / period) - 1)
        if node in self.silent:
            missing = min(missing, math.ceil(self.periods_allowed(node)))
        keep = 1.0 - 1.0 / self.settings.loss_memory
        self._missed[node] = self._missed.get(node, 0.0) * keep + missing
        self._expected[node] = self._expected.get(node, 0.0) * keep + missing + 1

    def loss(self, node: str) -> float:
        """The share of ``node``'s direct statuses that went missing lately (0 until one did)."""
        return self._missed.get(node, 0.0) / (self._expected.get(node, 0.0) + self.settings.clean_prior)

    def loss_bound(self, node: str) -> float:
        """`loss` plus two standard errors of it: the rate the detector plans for.

        The estimate of a few hundred statuses is off by a few points, and p^m is steep in p: sized
        for the estimate itself, a link losing 20 % read as 19 % made 1.3 false suspicions a day.
        """
        p = self.loss(node)
        if p <= 0.0:
            return 0.0
        n = self._expected.get(node, 0.0) + self.settings.clean_prior
        return min(0.95, p + 2.0 * math.sqrt(p * (1.0 - p) / n))

    def periods_allowed(self, node: str) -> float:
        """How many of ``node``'s status periods may pass without a status (see the module's rule)."""
        s = self.settings
        p = self.loss_bound(node)
        in_row = 1
        if p > 0.0 and math.isfinite(s.false_suspicions_per_day):  # infinite: two periods, whatever the loss
            statuses_a_day = DAY_S / self._period_s(node)
            budget = s.false_suspicions_per_day / max(1, len(self.tokens))  # shared by the peers watched
            # the least m with statuses_a_day * p**m <= budget
            in_row = max(1, math.ceil(math.log(budget / statuses_a_day) / math.log(p)))
        return min(s.max_periods, max(s.periods, in_row + 0.5))

    def limits(self) -> dict[str, float]:
        """Node in sight by its token (not already silent) -> how long its statuses may stay away."""
        if self._limits is None:
            self._limits = {node: self._limit(node) for node in self.tokens - self.silent}
        return dict(self._limits)

    def _limit(self, node: str) -> float:
        s = self.settings
        # a node at rest sends its status less often and says so: silent is silent for its cadence
        return silence_limit_s(self.periods_allowed(node), s.own_period_s, self._announced.get(node, 0.0), s.lease_s)

    def check(self, now: float) -> list[tuple[str, float]]:
        """The peers that went silent by ``now``, each with how long it has been silent (sorted)."""
        deadline = self.next_deadline()
        if deadline is None or now <= deadline:
            return []
        gone = []
        for node, limit in sorted(self.limits().items()):
            heard = self._heard.get(node)
            if heard is not None and now - heard > limit:
                self.silent.add(node)
                self.suspicions += 1
                gone.append((node, now - heard))
        self._changed(limits=True)
        return gone

    def next_deadline(self) -> float | None:
        """When the first watched peer counts as silent (wall time); None if none was heard yet.

        A loop that wakes only for its deadlines wakes for this one: a silent peer is found when its
        limit passes, not at whatever tick comes next.
        """
        if self._deadline is None:
            self._deadline = (next_silence_s(self._heard, self.limits()),)
        return self._deadline[0]
