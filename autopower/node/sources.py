"""Sources: the chains this node feeds from its own sensors, ticking on the mission clock.

A source runs for the run of its chain the plan says (`sync`); each tick of its period it takes a
capture (`due`: the node produces the frame, `NodeRuntime._produce`). A capture the node could not
take in time waits in the sensor's queue (`SENSOR_QUEUE` deep); older ones are overwritten, counted
as missed periods (apart, when the whole node was stopped). What a source produced is kept per run
(`totals`, `produced_by_run`) across its retirements and the process's restarts: a restarted
source goes on from its next seq in the same run, so no seq names two frames.
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Iterable, Iterator, Mapping

from autopower.model.scenario import Chain
from autopower.node.in_flight import ProducedByRun
from autopower.node.stages import SENSOR_QUEUE, STOPPED_AFTER_S, SourceRunner
from autopower.protocol import SourceStats

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts

SourceKey = tuple[str, str, int]  # (component type, robot, seed): what builds a source


class Sources:
    """The node's sources. It owns the running ones (`runners`), what each produced per run
    (`totals` of those retired, `produced_by_run`), those that hung (not restarted in their run)
    and the ones built ahead of the first plan. ``key_of(chain)`` says what builds a chain's
    source and ``build(key)`` builds it (raising what the component raises); ``count`` and
    ``tally`` are the node's counters."""

    def __init__(self, *, node: str, key_of: Callable[[Chain], SourceKey], build: Callable[[SourceKey], object],
                 count: Callable[..., None], tally: Callable[..., None]):
        self._node = node
        self._key_of = key_of
        self._build = build
        self._count = count
        self._tally = tally
        self.runners: dict[str, SourceRunner] = {}
        self.totals: dict[str, SourceStats] = {}  # the last run of each source retired here
        self.produced_by_run = ProducedByRun()  # what each source produced per run (`in_flight_at_stop`)
        self.hung: dict[str, int] = {}  # chain -> the run whose source hung here (not restarted)
        self._prepared: dict[SourceKey, object] = {}  # built before the mission, taken by the first run

    def __len__(self) -> int:
        return len(self.runners)

    def prepare(self, chains: Iterable[Chain]) -> None:
        """Build this node's sources now, before it joins: the first plan takes them ready-made.

        A camera renders its scene when built (~30 ms alone). Built at the first plan, every robot
        of a fleet does it at the same instant: 20 robots on 2 cores kept each loop busy 0.5-0.6 s,
        their statuses came late and peers took links for down, at a start with no fault at all.
        """
        for chain in chains:
            if chain.source != self._node or not chain.sourced:
                continue
            key = self._key_of(chain)
            try:
                self._prepared[key] = self._build(key)
            except Exception:  # noqa: BLE001 - the plan's own build says what is wrong, as ever
                continue

    def sync(self, running: Mapping[str, int], chains: Mapping[str, Chain], now: float) -> None:
        """Run this node's source of each chain ``running`` names, in that run; retire the others."""
        for name, runner in list(self.runners.items()):
            if running.get(name) != runner.run:
                self.retire(runner)
        for name, run in running.items():
            chain = chains.get(name)
            if (chain is None or chain.source != self._node or name in self.runners or self.hung.get(name) == run
                    or not chain.sourced):  # a DAG chain fed by other stages has no source to run
                continue
            key = self._key_of(chain)
            try:
                source = self._prepared.pop(key, None) or self._build(key)
            except Exception as exc:  # a broken component type must not take the agent down
                self._count("source-failed", f"{name}: {exc}", logging.ERROR)
                continue
            period = chain.period_s
            before = self.totals.get(name)
            self.runners[name] = SourceRunner(chain=chain, source=source, run=run,
                                              next_t=math.ceil(now / period - 1e-9) * period,
                                              produced_total=before.produced_total if before else 0,
                                              # like produced_total, over every run: summaries divide one
                                              # by the other (it restarted at 0 with each new run, so a
                                              # chain re-planned while late reported no missed period)
                                              missed=before.missed if before else 0,
                                              missed_stopped=before.missed_stopped if before else 0,
                                              # the same run after a restart: go on from its next seq
                                              seq=before.produced if before and before.run == run else 0)

    def retire(self, runner: SourceRunner) -> None:
        del self.runners[runner.chain.name]
        self.totals[runner.chain.name] = stats_of(runner)

    def hang(self, runner: SourceRunner) -> None:
        """A source that hung is stopped, and not started again in its run."""
        self.retire(runner)
        self.hung[runner.chain.name] = runner.run

    def resume(self, totals: Mapping[str, SourceStats]) -> None:
        """What a crashed process's sources had produced (its resume state): they go on from there."""
        self.totals.update(totals)
        for name, stats in totals.items():
            self.produced_by_run.note(name, stats.run, stats.produced)

    def produced(self, runner: SourceRunner) -> None:
        """``runner`` took its capture ``runner.seq`` (named before its frame leaves)."""
        runner.seq += 1
        runner.produced_total += 1
        self.produced_by_run.note(runner.chain.name, runner.run, runner.seq)

    def next_deadline(self) -> float | None:
        """Virtual time of the next source tick (None: nothing scheduled)."""
        return min((r.next_t for r in self.runners.values()), default=None)

    def due(self, now: float, away_s: float) -> Iterator[tuple[SourceRunner, float]]:
        """Each capture due by virtual time ``now``, in order per source, as (runner, tick time): the
        caller takes each (which may retire its runner) before it asks for the next. The captures
        older than the sensor's queue were overwritten: counted as missed (``away_s``: wall seconds
        since the node's last turn; a node away that long was stopped)."""
        for runner in list(self.runners.values()):
            if runner.next_t > now:
                continue
            period = runner.chain.period_s
            # the captures since the last tick wait in the sensor's queue; older ones were overwritten
            late = int((now - runner.next_t) // period) + 1 - SENSOR_QUEUE
            if late > 0:
                runner.missed += late
                runner.next_t += late * period
                self._tally("missed-periods", late)
                stopped = away_s >= STOPPED_AFTER_S
                if stopped:
                    runner.missed_stopped += late
                    self._tally("missed-periods-stopped", late)
                log.info("%s: source %s is %d period(s) late; skipped them%s", self._node, runner.chain.name, late,
                         f" (this node was stopped for {away_s:.1f} s)" if stopped else "")
            while runner.next_t <= now and runner.chain.name in self.runners:
                if runner.next_t + period <= now:
                    self._tally("late-captures")  # taken from the sensor's queue, after a later one was due
                yield runner, runner.next_t
                runner.next_t += period

    def stats(self) -> dict[str, SourceStats]:
        """Per chain this node ever sourced: its current run's figures, or its last run's."""
        out = {name: stats_of(runner) for name, runner in self.runners.items()}
        for name, stats in self.totals.items():
            out.setdefault(name, stats)
        return out


def stats_of(runner: SourceRunner) -> SourceStats:
    return SourceStats(run=runner.run, produced=runner.seq, missed=runner.missed,
                       produced_total=runner.produced_total, missed_stopped=runner.missed_stopped)
