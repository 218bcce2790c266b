"""What a node can prove at a clean stop: what its sources produced in each run, and which of a
chain's frames it still held (docs/reference/recording.md: every output in one class).

A chain's output that never reached its sink was either in flight when the team stopped or lost.
"In flight" is a claim the replay must be able to check, so each node, as it stops, says which
(chain, run, seq) it still had in hand: in custody (sent, not yet acknowledged, or a result held for
a sink out of reach), in its hold, waiting in a stage's sequence gate or start-up buffer, kept
for a stage with no host yet (orphans), or in the state of a stage it moved out whose new host has
not taken it yet (parked for a route, or shipped and not yet confirmed). A seq no node names is lost. And the number each source
produced in each run bounds the chain's tail: without it, outputs missing after the last one a
sink got were counted nowhere.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from autopower.errors import ProtocolError
from autopower.node.workers import worker_of
from autopower.protocol import ChainFrame, StateTransfer, decode

RunKey = tuple[str, int]  # (chain, run)


class ProducedByRun:
    """How many outputs each source produced in each run of its chain (seqs 0 .. n-1).

    Kept for every run the process saw, so a chain restarted in a new run still says how long its
    old run was; a restarted process starts from its resume file's count for the run it goes on."""

    def __init__(self) -> None:
        self._counts: dict[RunKey, int] = {}

    def note(self, chain: str, run: int, produced: int) -> None:
        key = (chain, run)
        if produced > self._counts.get(key, -1):
            self._counts[key] = produced

    def counts(self) -> dict[RunKey, int]:
        return dict(self._counts)


def frames_in_hand(chains: Iterable[str], places: Iterable[Iterable[ChainFrame]]) -> dict[RunKey, set[int]]:
    """(chain, run) -> the seqs of the frames in ``places`` that belong to one of ``chains`` (the
    scenario's chains: a DAG flow's pseudo-chain carries its producer's numbering, not its own)."""
    wanted = set(chains)
    out: dict[RunKey, set[int]] = {}
    for place in places:
        for frame in place:
            if frame.chain in wanted:
                out.setdefault((frame.chain, frame.run), set()).add(frame.seq)
    return out


def stage_frames(hosted: Mapping) -> list[ChainFrame]:
    """The inputs each hosted stage has taken but not run: waiting in its sequence gate or start-up
    buffer, or handed to its worker process with no result back yet."""
    out: list[ChainFrame] = []
    for h in hosted.values():
        out.extend(h.gate.pending.values())
        out.extend(h.buffer)
        worker = worker_of(h.component)
        if worker is not None:
            out.extend(frame for _, frame in worker.outstanding())
    return out


def transfer_frames(bodies: Iterable[bytes]) -> list[ChainFrame]:
    """The frames the states of stages moving out carry (`StateTransfer`: the inputs not run, the
    outputs not yet acknowledged), from their encoded bodies; one that does not decode carries none."""
    out: list[ChainFrame] = []
    for body in bodies:
        try:
            transfer = decode(body, StateTransfer)
        except ProtocolError:
            continue
        out.extend(transfer.pending)
        out.extend(transfer.outputs)
    return out
