"""Subgroup agreement without the base station: propose -> accept -> commit (two-phase commit).

When robots cannot reach the base station, those that still reach each other form a subgroup;
its leader (the lowest name) computes a reallocation (`autopower.policies.subgroup_reallocation`)
and runs one round of this protocol:

- the leader publishes `SubgroupPropose` (members, the placement after the round, the moves,
  one generation for all of them) and accepts it itself;
- a member accepts if it is in the members, has no other round pending and has no objection
  (the agent objects to a round that would start elsewhere a stage it runs), else rejects;
- the leader commits (`SubgroupDecision(commit=True)`) when every member accepted, and aborts
  on any reject, on its deadline, or when a member is lost; a member that accepted but hears no
  decision by its own (longer) deadline, or loses the leader, aborts locally.

A round is applied (``on_commit``) at most once per node (decided rounds are remembered), so a
repeated decision never runs a move twice; the moves themselves are the runtime's stop-and-copy
migrations, whose generations and sequence numbers keep every input processed exactly once.

Pure logic over a `Bus` and an injected clock: unit-tested with `InMemoryBus`.
"""

from __future__ import annotations

import enum
import logging
from dataclasses import dataclass, field
from typing import Callable

from autopower.errors import ProtocolError
from autopower.protocol import (
    Keys,
    SubgroupDecision,
    SubgroupMove,
    SubgroupPropose,
    SubgroupVote,
    decode,
    encode,
)
from autopower.runtime.bus import Bus
from autopower.runtime.signatures import Signing

log = logging.getLogger(__name__)

SUBGROUP_MESSAGES = (SubgroupPropose, SubgroupVote, SubgroupDecision)


class Phase(enum.Enum):
    IDLE = "idle"
    PROPOSED = "proposed"  # leader: waiting for votes
    ACCEPTED = "accepted"  # member: voted yes, waiting for the decision


@dataclass
class Round:
    proposal: SubgroupPropose
    deadline: float
    votes: dict[str, bool] = field(default_factory=dict)
    started: float = 0.0


class SubgroupAgreement:
    """One node's side of subgroup rounds (leader or member)."""

    def __init__(self, *, node: str, bus: Bus, keys: Keys, now: Callable[[], float],
                 on_commit: Callable[[SubgroupPropose], None], timeout_s: float = 1.0,
                 on_abort: Callable[[str, str], None] | None = None, signing: Signing | None = None,
                 objection: Callable[[SubgroupPropose], str | None] | None = None,
                 relay: Callable[..., None] | None = None):
        """With ``signing``, every proposal, vote and decision is signed, and one that its claimed
        author (the leader, the voter) did not sign is dropped: a robot cannot vote for another.

        ``relay(dests, key, payload, reliable=...)`` (`Relayer.send_beyond_sight`): each message is
        also relayed to those it is for that a publish does not reach. A round's members are every
        robot the leader reaches, through others too, and Zenoh peers do not relay: published only,
        a proposal never reached a member behind a cut link, which never voted, and every round
        timed out while the stages of the laptop ran nowhere."""
        self.node = node
        self.relay = relay
        self.signing = signing
        self.bus = bus
        self.keys = keys
        self.now = now
        self.on_commit = on_commit
        self.on_abort = on_abort or (lambda round_id, why: None)
        self.objection = objection or (lambda proposal: None)
        self.timeout_s = timeout_s
        self.phase = Phase.IDLE
        self.round: Round | None = None
        self.decided: dict[str, bool] = {}  # round id -> committed?
        self.counter = 0
        self.committed = 0
        self.aborted = 0
        self.agreement_s: list[float] = []  # leader: propose -> commit, wall seconds

    # ---- leader ----------------------------------------------------------------------------------
    def propose(self, members: tuple[str, ...], placement: dict[str, str], moves: tuple[SubgroupMove, ...],
                generation: int, reason: str) -> str | None:
        """Start a round as leader; None if another round is pending here."""
        if self.phase is not Phase.IDLE:
            return None
        self.counter += 1
        round_id = f"{self.node}-{self.counter}-{generation}"
        proposal = SubgroupPropose(round_id=round_id, leader=self.node, members=tuple(members),
                                   placement=dict(placement), moves=tuple(moves), generation=generation,
                                   reason=reason)
        now = self.now()
        self.round = Round(proposal=proposal, deadline=now + self.timeout_s, started=now)
        self.round.votes[self.node] = True
        self.phase = Phase.PROPOSED
        log.info("subgroup %s: proposing %s to %s (%d moves): %s", self.node, round_id, ", ".join(members),
                 len(moves), reason)
        self._publish(proposal, members)
        self._maybe_decide()
        return round_id

    def _maybe_decide(self) -> None:
        r = self.round
        if self.phase is not Phase.PROPOSED or r is None:
            return
        if any(v is False for v in r.votes.values()):
            self._finish(False, "a member rejected")
        elif set(r.proposal.members) <= {n for n, v in r.votes.items() if v}:
            self._finish(True, "every member accepted")

    def _finish(self, commit: bool, reason: str) -> None:
        r = self.round
        self._publish(SubgroupDecision(round_id=r.proposal.round_id, commit=commit, reason=reason), r.proposal.members)
        if commit:
            self.agreement_s.append(self.now() - r.started)
        self._apply(r.proposal, commit, reason)

    # ---- both ------------------------------------------------------------------------------------
    def _apply(self, proposal: SubgroupPropose, commit: bool, reason: str) -> None:
        self.phase = Phase.IDLE
        self.round = None
        if proposal.round_id in self.decided:
            return
        self.decided[proposal.round_id] = commit
        if commit:
            self.committed += 1
            log.info("subgroup %s: round %s committed (%s)", self.node, proposal.round_id, reason)
            self.on_commit(proposal)
        else:
            self.aborted += 1
            log.info("subgroup %s: round %s aborted (%s)", self.node, proposal.round_id, reason)
            self.on_abort(proposal.round_id, reason)

    def on_message(self, payload: bytes) -> None:
        try:
            msg = decode(payload, SUBGROUP_MESSAGES)
        except ProtocolError as exc:
            log.warning("subgroup %s: dropped a garbled message: %s", self.node, exc)
            return
        if isinstance(msg, SubgroupPropose):
            if self._authentic(msg, msg.leader):
                self._on_propose(msg)
        elif isinstance(msg, SubgroupVote):
            r = self.round
            if self.phase is Phase.PROPOSED and r and msg.round_id == r.proposal.round_id \
                    and msg.node in r.proposal.members and self._authentic(msg, msg.node):
                r.votes[msg.node] = msg.accept
                self._maybe_decide()
        elif isinstance(msg, SubgroupDecision):
            r = self.round
            if self.phase is Phase.ACCEPTED and r and msg.round_id == r.proposal.round_id \
                    and self._authentic(msg, r.proposal.leader):
                self._apply(r.proposal, msg.commit, msg.reason)

    def _on_propose(self, msg: SubgroupPropose) -> None:
        if msg.leader == self.node or self.node not in msg.members or msg.round_id in self.decided:
            return
        if self.phase is not Phase.IDLE:
            why = f"busy with round {self.round.proposal.round_id}" if self.round else "busy"
            self._vote(msg, False, why)
            return
        why = self.objection(msg)
        if why is not None:
            log.info("subgroup %s: rejecting round %s: %s", self.node, msg.round_id, why)
            self._vote(msg, False, why)
            return
        self.round = Round(proposal=msg, deadline=self.now() + 2 * self.timeout_s, started=self.now())
        self.phase = Phase.ACCEPTED
        self._vote(msg, True, "")

    def _vote(self, msg: SubgroupPropose, accept: bool, reason: str) -> None:
        self._publish(SubgroupVote(round_id=msg.round_id, node=self.node, accept=accept, reason=reason), (msg.leader,))

    def _publish(self, msg, dests) -> None:
        """To every node in sight, and relayed to those of ``dests`` out of it."""
        payload = encode(self.signing.sign(msg) if self.signing is not None else msg)
        self.bus.publish(self.keys.subgroup, payload)
        if self.relay is not None:
            self.relay([d for d in dests if d != self.node], self.keys.subgroup, payload)

    def _authentic(self, msg, author: str) -> bool:
        return self.signing is None or self.signing.check(msg, author, f"a subgroup {type(msg).__name__}")

    def on_timer(self) -> None:
        r = self.round
        if r is None or self.now() < r.deadline:
            return
        if self.phase is Phase.PROPOSED:
            missing = sorted(set(r.proposal.members) - set(r.votes))
            self._finish(False, f"timeout: no vote from {', '.join(missing)}")
        elif self.phase is Phase.ACCEPTED:
            self._apply(r.proposal, False, "timeout: no decision from the leader")

    def on_member_lost(self, node: str) -> None:
        r = self.round
        if r is None or node not in r.proposal.members + (r.proposal.leader,):
            return
        if self.phase is Phase.PROPOSED:
            self._finish(False, f"{node} was lost")
        elif self.phase is Phase.ACCEPTED and node == r.proposal.leader:
            # only the leader's loss: another member's loss is the leader's call (it may have
            # committed already with that member's vote)
            self._apply(r.proposal, False, f"the leader {node} was lost")

    @property
    def busy(self) -> bool:
        return self.phase is not Phase.IDLE
