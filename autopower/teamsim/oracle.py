"""The oracle of a simulated run: it trusts what the team did, never what the team says about it.

What it records as the run goes:

- production: every frame a source emitted (chain, run, seq), when, at which trace event;
- deliveries: every output a sink handed on, counted once its sink committed it (the status
  that acknowledges it went out: what a recording keeps); one handed on twice is a duplicate;
- the budget: outputs a node let go by design and said so per output (a full hold's drops, a
  latest-only chain's results a newer one replaced in a hold (in the budget only if a later output
  of their run is delivered), outputs that died in a crashed process's memory), and the chains the operator stopped (from
  the fault schedule, not from the team); and, from the production itself, the undelivered tail
  of a run its chain left for a newer one (the chain was restarted without its state: what the
  old run had in flight has no consumer any more);
- errors: exceptions that escaped the core, stages stopped for a skipped or repeated input.

After the run `verdict` judges every output produced before the judging horizon: delivered
exactly once, or in the budget; anything else is lost.
"""

from __future__ import annotations

from dataclasses import dataclass, field

Key = tuple[str, int, int]  # (chain, run, seq)

STOP_WINDOW_S = 5.0  # outputs produced this long before an operator stopped their chain may die with it


@dataclass(frozen=True)
class Violation:
    invariant: str
    detail: str
    t: float  # simulated seconds
    event: int  # the trace event where it shows (0: at the end of the run)

    def to_json(self) -> dict:
        return {"invariant": self.invariant, "detail": self.detail, "t": round(self.t, 6), "event": self.event}


@dataclass
class ChainCounts:
    produced: int = 0
    delivered: int = 0
    lost: int = 0
    duplicated: int = 0
    dropped_by_budget: int = 0
    budget: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"produced": self.produced, "delivered": self.delivered, "lost": self.lost,
                "duplicated": self.duplicated, "dropped_by_budget": self.dropped_by_budget,
                "budget": dict(sorted(self.budget.items()))}


class Ledger:
    def __init__(self, chains: list[str]):
        self.chains = list(chains)
        self.produced: dict[Key, tuple[float, int]] = {}
        self.delivered: dict[Key, tuple[float, int]] = {}
        self.budget: dict[Key, str] = {}
        self.stops: list[tuple[str, float, float]] = []  # (chain, disabled at, enabled at)
        self.violations: list[Violation] = []
        self.duplicates: dict[str, int] = {}
        # the outputs some kill took: the killed process had them, no other did (`teamsim.evidence`)
        self.died_in_kills: set[Key] = set()

    # ---- as the run goes -----------------------------------------------------------------------
    def on_produced(self, key: Key, t: float, event: int) -> None:
        if key in self.produced:
            self.violate("sources", f"{key[0]} run {key[1]} seq {key[2]} produced again (first at "
                         f"{self.produced[key][0]:.3f} s): two frames under one name", t, event)
            return
        self.produced[key] = (t, event)

    def on_delivered(self, key: Key, t: float, event: int, data: bytes, expected: bytes | None) -> None:
        if key in self.delivered:
            self.duplicates[key[0]] = self.duplicates.get(key[0], 0) + 1
            self.violate("exactly-once", f"{key[0]} run {key[1]} seq {key[2]} delivered again (first at "
                         f"{self.delivered[key][0]:.3f} s)", t, event)
            return
        self.delivered[key] = (t, event)
        if expected is not None and data != expected:
            self.violate("outputs", f"{key[0]} run {key[1]} seq {key[2]}: the sink got other bytes than its chain "
                         "computes from that seq's input", t, event)

    def let_go(self, key: Key, reason: str) -> None:
        self.budget.setdefault(key, reason)

    def killed_with(self, keys: set[Key]) -> None:
        """A process was killed with these outputs in its hands only."""
        self.died_in_kills |= keys

    def operator_stop(self, chain: str, t_off: float, t_on: float) -> None:
        self.stops.append((chain, t_off, t_on))

    def violate(self, invariant: str, detail: str, t: float, event: int) -> None:
        self.violations.append(Violation(invariant, detail, t, event))

    # ---- after the run ---------------------------------------------------------------------------
    def _stopped(self, chain: str, t: float) -> bool:
        return any(c == chain and t_off - STOP_WINDOW_S <= t <= t_on for c, t_off, t_on in self.stops)

    def verdict(self, horizon_t: float) -> dict[str, ChainCounts]:
        """Per chain counts; a lost output (the first one per chain) and each unproduced delivery
        become violations. An output labelled died with a crashed process counts so only if a kill
        took it (`killed_with`); otherwise it is judged as if unlabelled."""
        counts = {c: ChainCounts() for c in self.chains}
        first_lost: dict[str, tuple[Key, float, int]] = {}
        mislabelled: dict[str, int] = {}  # chain -> lost outputs a restarted process said died with it
        newest_run: dict[str, int] = {}
        for chain, run, _ in self.produced:
            newest_run[chain] = max(newest_run.get(chain, run), run)
        last_delivered: dict[tuple[str, int], int] = {}
        for chain, run, seq in self.delivered:
            last_delivered[(chain, run)] = max(last_delivered.get((chain, run), seq), seq)
        for key, (t, event) in sorted(self.produced.items(), key=lambda kv: kv[1][1]):
            if t > horizon_t:
                continue
            c = counts[key[0]]
            c.produced += 1
            if key in self.delivered:
                c.delivered += 1
                continue
            reason = self.budget.get(key) or ("operator-stopped" if self._stopped(key[0], t) else None)
            labelled = reason == "died-with-process"
            if labelled and key not in self.died_in_kills:
                reason = None  # a label without evidence: no kill took it (what it was is decided below)
            if reason == "superseded" and key[2] > last_delivered.get(key[:2], -1):
                reason = None  # replaced by a newer result that never arrived either: nothing did its job
            if reason is None and key[1] < newest_run[key[0]] and key[2] > last_delivered.get(key[:2], -1):
                reason = "run-ended"  # the tail of a run its chain left for a newer one (restarted without state)
            if reason is not None:
                c.dropped_by_budget += 1
                c.budget[reason] = c.budget.get(reason, 0) + 1
                continue
            c.lost += 1
            first_lost.setdefault(key[0], (key, t, event))
            if labelled:
                mislabelled[key[0]] = mislabelled.get(key[0], 0) + 1
        for chain, (key, t, event) in first_lost.items():
            said = (f"; {mislabelled[chain]} of them labelled died with a crashed process, though no kill took "
                    "them" if chain in mislabelled else "")
            self.violate("exactly-once", f"{chain}: {counts[chain].lost} output(s) lost, the first run {key[1]} "
                         f"seq {key[2]} (produced at {t:.3f} s, never delivered){said}", t, event)
        for key, (t, event) in sorted(self.delivered.items(), key=lambda kv: kv[1][1]):
            if key not in self.produced:
                self.violate("outputs", f"{key[0]} run {key[1]} seq {key[2]} delivered, never produced", t, event)
                break
        for chain, n in self.duplicates.items():
            counts[chain].duplicated = n
        return counts
