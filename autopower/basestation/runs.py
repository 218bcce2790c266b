"""The chains' runs: which run each chain is in, and which chains run.

A chain's run is a number its source stamps on every input; a chain that stopped entirely starts
the next run (its sequence from 0), and a stage replacing a dead host in a chain that keeps running
continues the run from the first input it sees. After a takeover, a chain whose run no robot has
said yet is neither assigned afresh nor declared running until it is known (`learn`).
"""

from __future__ import annotations

from autopower.model.scenario import Chain
from autopower.protocol import NodeStatus


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

    def adopt(self, runs: dict[str, int], unknown: set[str]) -> None:
        """The runs of a team taken over (their sequences go on), and the chains whose run is still to be said."""
        for chain, run in runs.items():
            self.runs[chain] = run
            self.run_live[chain] = True  # its sequence goes on: a new instance starts where inputs are
        self.runs_unknown |= unknown

    def run_for(self, chain: Chain, busy: bool) -> tuple[int, int | None, bool]:
        """(the run a fresh instance of a stage of ``chain`` joins, the seq it starts at, whether that
        run is a restart). ``busy``: a stage of the chain is placed or moving. A chain that had stopped
        entirely (not busy, not running) starts a new run at seq 0; otherwise the instance continues
        the run from the first input it sees."""
        restarted = False
        if not busy and chain.name not in self.running:
            self.runs[chain.name] = self.runs.get(chain.name, -1) + 1
            self.run_live[chain.name] = False
            restarted = self.runs[chain.name] > 0  # its first run is the mission's start
        return self.runs[chain.name], (None if self.run_live.get(chain.name) else 0), restarted

    def update(self, chains: list[Chain], target: dict[str, str], placement: dict[str, str]) -> None:
        """The chains that run: every stage targeted and placed, and the run known."""
        running = {}
        for chain in chains:
            names = [s.name for s in chain.stages]
            if chain.name in self.runs_unknown:
                continue  # not declared running before its run is known (`learn`)
            if names and all(s in target and s in placement for s in names):
                running[chain.name] = self.runs[chain.name]
                self.run_live[chain.name] = True
        self.running = running

    def learn(self, status: NodeStatus, chain_named) -> list[str]:
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
            learned.append(f"{name} run {self.runs.get(name, 'new')}")
        return learned
