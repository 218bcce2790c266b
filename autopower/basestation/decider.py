"""Asking the policy: on the caller's thread, or on a thread of its own while the base station's loop goes on.

A decision of a large team is seconds of work (a 30-robot mission start is a MILP of 2-3 s in
HiGHS; a 20-robot cut's decision 0.45 s of planner Python). On the loop, those seconds are
seconds in which no status is read and none is sent: robots take the base station for gone,
their links go down, and every link down is another decision (the 50-robot cascade). So the live
base station asks on a thread: the loop hands over a `TeamState` (a snapshot the policy owns),
goes on, and carries the answer out when it comes. HiGHS releases the GIL while it solves, so the
loop runs at full speed through a MILP; the planner's Python shares the GIL with it.

The simulator and the unit tests ask inline: the answer is there when `ask` returns, and a run
is the same run every time.

One question at a time: the policy keeps state between decisions (the rebalance policy's last
option) and is not shared between threads. What happens while a question is out waits for the
next one (`Deciding.replan` queues its reason).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable

from autopower.errors import AutoPowerError
from autopower.policies import Decision, Policy, TeamState


@dataclass(frozen=True)
class Answer:
    """The policy's answer to one question: a decision, None (keep what runs), or the error that
    says it found nothing (`failure`: the policy's own bug, raised again on the loop)."""

    state: TeamState
    reason: str
    decision: Decision | None
    error: AutoPowerError | None
    took_s: float
    failure: BaseException | None = None


@dataclass(frozen=True)
class AwaitDecision:
    """An operator's command whose reply waits for the decision that carries it out: the answer
    to question number ``ticket`` (`Coordinator.asked`), or none coming (`reply_when_decided`)."""

    ticket: int


class Decider:
    """Asks ``policy`` one question at a time. ``on_answer``: None asks inline (the answer is
    there when `ask` returns); given, each question runs on a thread of its own and
    ``on_answer()`` is called from that thread when its answer is in (the process wakes its loop,
    which then takes it with `take`)."""

    def __init__(self, policy: Policy, *, perf_fn: Callable[[], float] = time.perf_counter,
                 on_answer: Callable[[], object] | None = None):
        self.policy = policy
        self._perf = perf_fn
        self._on_answer = on_answer
        self._lock = threading.Lock()
        self._answer: Answer | None = None
        self._thread: threading.Thread | None = None
        self._asked = False  # a question is out and its answer not yet taken
        # answers whose configuration the policy did not prove optimal (`Decision.proven_optimal`),
        # and the largest MILP gap among them (None: none, or no gap known)
        self.unproven = 0
        self.unproven_max_gap: float | None = None

    @property
    def on_thread(self) -> bool:
        return self._on_answer is not None

    @property
    def busy(self) -> bool:
        """A question is out (or its answer waits to be taken): ask the next one after `take`."""
        return self._asked

    def ask(self, state: TeamState, reason: str) -> None:
        if self._asked:
            raise RuntimeError("Decider.ask: the last answer has not been taken yet")
        self._asked = True
        if self._on_answer is None:
            try:
                self._answer = self._decide(state, reason)
            except BaseException:
                self._asked = False  # the policy's bug went up to the caller: the next question may be asked
                raise
            return
        self._thread = threading.Thread(target=self._decide_on_thread, args=(state, reason),
                                        name="autopower-decide", daemon=True)
        self._thread.start()

    def take(self) -> Answer | None:
        """The answer, once it is in (None before); the next question may then be asked."""
        with self._lock:
            answer, self._answer = self._answer, None
        if answer is not None:
            self._asked = False
            self._thread = None
        return answer

    def close(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for a question still out; True when none is (the thread is a
        daemon: a process stopping in the middle of a MILP does not wait for it past that)."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
            return not thread.is_alive()
        return True

    def _decide_on_thread(self, state: TeamState, reason: str) -> None:
        answer = self._decide(state, reason)
        with self._lock:
            self._answer = answer
        self._on_answer()

    def _decide(self, state: TeamState, reason: str) -> Answer:
        started = self._perf()
        decision, error, failure = None, None, None
        try:
            decision = self.policy.decide(state)
        except AutoPowerError as exc:  # InfeasibleError, or a state the policy rejects
            error = exc
        except Exception as exc:  # the policy's bug: raised again where the answer is taken
            if self._on_answer is None:
                raise
            failure = exc
        if decision is not None and decision.proven_optimal is False:
            self.unproven += 1
            if decision.mip_gap is not None:
                self.unproven_max_gap = max(self.unproven_max_gap or 0.0, decision.mip_gap)
        return Answer(state=state, reason=reason, decision=decision, error=error,
                      took_s=self._perf() - started, failure=failure)
