"""Who a robot sees directly: the transport's liveliness tokens, checked by the statuses that arrive.

A peer is in direct sight while its liveliness token is (the transport's lease: a session that
died is gone within it) *and* its statuses keep arriving directly. A token alone is not enough: a
link that fails in one direction, or a peer whose loop is stuck, keeps its session (and token)
while nothing it says arrives. So a peer whose direct statuses stay away for ``periods`` of the
status period it announced (ours if it announced none) counts as silent, out of sight, never
sooner than the lease (a team configured with a long lease, for radios that stay saturated for
seconds, must not have its peers declared gone by this detector first). Its next direct status
brings it back.

`PeerWatch` owns that state and nothing else. Time comes in with each call; what changed goes out
as return values, for the process to act on (tell its runtime, its relayer, its subgroup rounds).
"""

from __future__ import annotations

from dataclasses import dataclass

from autopower.runtime.cadence import next_silence_s, silence_limit_s


@dataclass(frozen=True)
class WatchSettings:
    periods: float = 2.0  # announced status periods a peer may stay silent
    own_period_s: float = 0.5  # our status period: a peer that announced none is judged by it
    lease_s: float = 0.5  # the transport's lease: never sooner than this


class PeerWatch:
    def __init__(self, settings: WatchSettings):
        self.settings = settings
        self.tokens: set[str] = set()  # nodes whose liveliness token we see
        self.silent: set[str] = set()  # nodes with a token but no direct status for too long
        self._heard: dict[str, float] = {}  # node -> wall time of its last status received directly
        self._announced: dict[str, float] = {}  # node -> the status period it said it keeps
        self.suspicions = 0  # peers declared silent (each later heard again was a false suspicion)
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
        return False

    def on_status(self, node: str, next_status_s: float, now: float) -> bool:
        """A status of ``node`` arrived directly (not relayed); True: it is back in sight (was silent)."""
        self._changed(limits=self._announced.get(node) != next_status_s)
        self._announced[node] = next_status_s
        self._heard[node] = now
        if node in self.silent and node in self.tokens:
            self.silent.discard(node)
            self._changed(limits=True)
            return True
        return False

    def limits(self) -> dict[str, float]:
        """Node in sight by its token (not already silent) -> how long its statuses may stay away."""
        if self._limits is None:
            s = self.settings
            # a node at rest sends its status less often and says so: silent is silent for its cadence
            self._limits = {node: silence_limit_s(s.periods, s.own_period_s, self._announced.get(node, 0.0),
                                                  s.lease_s) for node in self.tokens - self.silent}
        return dict(self._limits)

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
