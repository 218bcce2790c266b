"""The chains' runs: which run each chain is in, and which chains run.

A chain's run is a number its source stamps on every input: a seq names one input of its run
only, so a run goes on only while its source's seqs go on. A chain that keeps running while a
stage replaces a dead host goes on in its run: the new instance starts from the first input it
sees. A chain that stopped entirely and runs again:

- goes on in its run (`run_for`: "resumed") when it stopped for a fault (its source robot out of
  reach: killed, cut off, frozen, or this base station's restart) and its source robot's process
  holds the run's position: the robot stayed in the base station's sight since the chain stopped
  and no status says it runs another process since, or the status it sent since it came back says
  it is the process the base station knew before the stop (it was cut off, frozen) or a restarted
  one that took that run's position from its predecessor's saved state (`NodeStatus.resumed`). Its
  fresh instances start from the oldest input their producer still holds, so the inputs it had not
  run when it stopped are run, not abandoned;
- starts the next run, from seq 0, when its source robot's process does not hold the position (a
  process restarted before its first resume snapshot sources the run from seq 0 again: going on
  in the run would give two inputs each seq), when the operator stopped it (or a failed component,
  which stops it the same way), and when it has no source (its fan-in stage names the outputs: a
  fresh instance would name them from 0 again);
- waits, unassigned, while that is not known: its source robot out of reach, or back in sight
  without a status since from a process that runs a plan (a restarted process takes its saved
  state up at its first plan).

After a takeover, a chain whose run no robot has said yet is neither assigned afresh nor declared
running until it is known (`learn`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from autopower.model.scenario import Chain
from autopower.protocol import NodeStatus


@dataclass(frozen=True)
class SourceSight:
    """What the base station knows of a chain's source robot now (`Coordinator.source_sight`)."""

    sighting: int | None  # which time it came into sight (a count); None: out of sight
    status: NodeStatus | None  # its last status (None: none yet)
    # that status came since the robot last came into sight, from a process that runs a plan (it
    # has taken up its saved state, if any): it speaks for the process the robot runs now
    current: bool

    @property
    def process(self) -> int | None:
        return self.status.process if self.status is not None else None


class ChainRuns:
    """The run of each chain, whether it produced anything yet, and the chains that run (the plan's ``running``)."""

    def __init__(self):
        self.runs: dict[str, int] = {}  # chain -> current run number
        # chains of a team taken over whose source robot had not spoken: their run is the one it
        # reports (`learn`); until then none of their stages is assigned afresh and the chain is
        # not declared running (a run made up here could be older than the robot's, whose outputs
        # every sink would then drop as stale)
        self.runs_unknown: set[str] = set()
        self.run_live: dict[str, bool] = {}  # has the current run produced anything yet
        self.running: dict[str, int] = {}  # chain -> run, for the chains all of whose stages run where targeted
        # chains whose run the operator (or a failed component) ended: they start the next one when they run again
        self.ended: set[str] = set()
        # chain -> (the sighting of its source robot when the chain stopped, None: out of sight; the
        # process it last heard from it then, `NodeStatus.process`): who held the run's position
        self.stopped: dict[str, tuple[int | None, int | None]] = {}

    def adopt(self, runs: dict[str, int], unknown: set[str],
              holders: dict[str, tuple[int | None, int | None]] | None = None) -> None:
        """The runs of a team taken over (their sequences go on), and the chains whose run is still to
        be said; ``holders``: chain -> (the sighting of its source robot, the process that reported its run)."""
        for chain, run in runs.items():
            self.runs[chain] = run
            self.run_live[chain] = True  # its sequence goes on: a new instance starts where inputs are
        self.stopped.update(holders or {})
        self.runs_unknown |= unknown

    def run_for(self, chain: Chain, busy: bool, source: SourceSight) -> tuple[int, int | None, str]:
        """(the run a fresh instance of a stage of ``chain`` joins, the seq it starts at (None: the first
        input it sees), how): see the module docstring. ``busy``: a stage of the chain is placed or
        moving; ``source``: what the base station knows of the chain's source robot now. How:
        "continues" (busy, or the chain runs), "first" (its first run), "resumed", "restarted" (its
        source robot's process does not hold the run's position: the next run), "new" (the operator
        or a failed component stopped it, or it has no source: the next run), or "waiting" (for its
        source robot's process to say what it holds: nothing is assigned)."""
        name = chain.name
        if busy or name in self.running:
            return self.runs[name], (None if self.run_live.get(name) else 0), "continues"
        if name not in self.runs or name in self.ended or not chain.sourced:
            return self._next_run(name), 0, "new" if self.runs[name] > 0 else "first"
        run = self.runs[name]
        if not self.run_live.get(name):  # never declared running: its source made none of its seqs
            return run, 0, "resumed"
        if source.sighting is None:
            return run, None, "waiting"
        seen, holder = self.stopped.get(name, (None, None))
        if seen is not None and seen == source.sighting and (holder is None or source.process in (None, holder)):
            # in sight throughout (its liveliness token ends with its process), and no status says
            # it runs another process since: the one that held the run
            return run, None, "resumed"
        if not source.current:
            return run, None, "waiting"
        stats = source.status.sources.get(name)
        # the process holds the run's position: it is the one that held it, or it took it up from
        # the one before (a restarted process that did neither sources the run from seq 0 again)
        if stats is not None and stats.run == run and (
                source.process == holder or source.status.resumed.get(name) == run):
            return run, None, "resumed"
        return self._next_run(name), 0, "restarted"

    def _next_run(self, name: str) -> int:
        self.ended.discard(name)
        self.runs[name] = self.runs.get(name, -1) + 1
        self.run_live[name] = False
        return self.runs[name]

    def update(self, chains: list[Chain], target: dict[str, str], placement: dict[str, str],
               disabled: set[str], sight_of: Callable[[str], SourceSight]) -> None:
        """The chains that run: every stage targeted and placed, and the run known. A ``disabled``
        chain that does not run has its run ended (`run_for`). A chain that stops notes what the base
        station knows of its source robot then (``sight_of``: robot -> `SourceSight`)."""
        running = {}
        for chain in chains:
            names = [s.name for s in chain.stages]
            if chain.name in self.runs_unknown:
                continue  # not declared running before its run is known (`learn`)
            if names and all(s in target and s in placement for s in names):
                running[chain.name] = self.runs[chain.name]
                self.run_live[chain.name] = True
            elif chain.name in self.running:
                sight = sight_of(chain.source)
                self.stopped[chain.name] = (sight.sighting, sight.process)
        self.running = running
        self.ended.update(name for name in disabled if name not in running)

    def learn(self, status: NodeStatus, chain_named, sight_of: Callable[[str], SourceSight]) -> list[str]:
        """The run of each chain ``status.node`` is the source of, when a takeover did not know it;
        what was learned, in words (``chain_named``: name -> `Chain`).

        A source robot reports the last run of every chain it ever ran (`NodeRuntime.status`); one
        that reports none for a chain never ran it, and the chain starts a fresh run. A fan-in chain
        has no source: its stage names its outputs, and its sink (its ``source`` node) reports the
        last run it got, once its mission has started (its ledgers are kept across a restart).
        """
        learned = []
        for name in sorted(self.runs_unknown):
            chain = chain_named(name)
            if chain.source != status.node or (not chain.sourced and status.mission is None):
                continue
            self.runs_unknown.discard(name)
            stats = status.sources.get(name) if chain.sourced else status.sinks.get(name)
            if stats is not None:
                self.runs[name] = max(self.runs.get(name, -1), stats.run)
                self.run_live[name] = True  # its sequence goes on
                if chain.sourced and stats.run == self.runs[name]:  # this process holds the run's position
                    self.stopped[name] = (sight_of(status.node).sighting, status.process)
            learned.append(f"{name} run {self.runs.get(name, 'new')}")
        return learned
