"""The chains' runs: which run each chain is in, and which chains run.

A chain's run is a number its source stamps on every input. A chain the operator stopped (or a
failed component, which stops it the same way), and a chain with no source (its fan-in stage names
the outputs), starts the next run when it runs again (its sequence from 0). A chain that stopped
for any other reason (a fault: its source robot was out of reach) goes on in its run, as does a
chain that keeps running while a stage replaces a dead host: the new instances start from the
first input they see, the oldest their producer still holds, so the inputs the chain had not run
when it stopped are run, not abandoned. After a takeover, a chain whose run no robot has said yet
is neither assigned afresh nor declared running until it is known (`learn`).
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
        # chains whose run the operator (or a failed component) ended: they start the next one when they run again
        self.ended: set[str] = set()

    def adopt(self, runs: dict[str, int], unknown: set[str]) -> None:
        """The runs of a team taken over (their sequences go on), and the chains whose run is still to be said."""
        for chain, run in runs.items():
            self.runs[chain] = run
            self.run_live[chain] = True  # its sequence goes on: a new instance starts where inputs are
        self.runs_unknown |= unknown

    def run_for(self, chain: Chain, busy: bool) -> tuple[int, int | None, str]:
        """(the run a fresh instance of a stage of ``chain`` joins, the seq it starts at (None: the first
        input it sees), how: "first" (the chain's first run), "new" (a chain the operator or a failed
        component stopped runs again, and a chain with no source: the next run, from seq 0),
        "resumed" (a sourced chain that stopped for another reason runs again in its run) or
        "continues" (``busy``: a stage of the chain is placed or moving, or the chain runs)."""
        name = chain.name
        if busy or name in self.running:
            return self.runs[name], (None if self.run_live.get(name) else 0), "continues"
        # a chain with no source (a fan-in stage's outputs are named by the stage) cannot go on in its
        # run with a fresh instance: that one would name its steps from 0 again
        if name not in self.runs or name in self.ended or not chain.sourced:
            self.ended.discard(name)
            self.runs[name] = self.runs.get(name, -1) + 1
            self.run_live[name] = False
            return self.runs[name], 0, "new" if self.runs[name] > 0 else "first"
        return self.runs[name], (None if self.run_live.get(name) else 0), "resumed"

    def update(self, chains: list[Chain], target: dict[str, str], placement: dict[str, str],
               disabled: set[str]) -> None:
        """The chains that run: every stage targeted and placed, and the run known. A ``disabled``
        chain that does not run has its run ended (`run_for`)."""
        running = {}
        for chain in chains:
            names = [s.name for s in chain.stages]
            if chain.name in self.runs_unknown:
                continue  # not declared running before its run is known (`learn`)
            if names and all(s in target and s in placement for s in names):
                running[chain.name] = self.runs[chain.name]
                self.run_live[chain.name] = True
        self.running = running
        self.ended.update(name for name in disabled if name not in running)

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
