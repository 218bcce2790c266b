"""What a node runtime is given when it is built: its ways out to the process that owns it.

A `NodeRuntime` has no sockets, files, threads or clocks of its own. The process around it (a
robot's agent, the base station, a simulator's shell, a test) gives it, once, at construction:

- `NodePorts`: how a message for one node leaves (the process's `Relayer.send`, which reaches a
  node out of direct sight through others), who is in direct sight (what may be forwarded on
  arrival, `autopower.node.relaying`), and how a stage worker's result wakes the process's loop;
- `NodeStores`: what outlives the process: the journal of results held for a sink out of reach
  (`HeldStore`), the sink ledgers (`SinkStore`), the state a crashed process saved (applied at
  the first plan of the same mission) and where each seq a source produced is noted first;

and whoever wants the sink's news (the recorder, the simulator's oracle, a test) registers a
`SinkListener` with `NodeRuntime.listen`. Nothing is assigned into a runtime from outside after
it is built: what it may use is in its constructor's arguments, so a reader of the runtime sees
every way out in one place.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from autopower.node.held_store import HeldStore
    from autopower.node.sink_store import SinkStore
    from autopower.node.stages import SourceRunner


def _nobody_in_sight(node: str) -> bool:
    return False


@dataclass(frozen=True)
class NodePorts:
    """How the node's messages leave and how its process is woken. The defaults are a process
    without a relayer: each message is published straight on the bus, nothing is forwarded on
    arrival (the loop's `send_to` decides), and worker results wait for the next timer turn."""

    # (dest, key, payload, *, reliable=True) -> anything; None: the bus's publish
    send_to: Callable[..., object] | None = None
    in_sight: Callable[[str], bool] = _nobody_in_sight  # who this node reaches directly now
    notify_work: Callable[[], None] | None = None  # a stage worker's result is in (posts to the loop)


@dataclass(frozen=True)
class NodeStores:
    """What survives the process. None of them: a crash loses what only its memory held."""

    held_store: "HeldStore | None" = None  # results held for a sink out of reach, on disk
    sink_store: "SinkStore | None" = None  # the sink ledgers: an output delivered before a crash is not again
    resume_from: dict | None = None  # a crashed process's saved state (`NodeRuntime.resume_state`)
    # a source advanced (noted before its frame leaves: a crash after it never reuses the seq)
    on_produced: "Callable[[SourceRunner], None] | None" = None


def _ignore(*args) -> None:
    return None


@dataclass(frozen=True)
class SinkListener:
    """Who hears what happens to a chain's outputs at this node; each call names (chain, run, seq).

    - ``output(chain, run, seq, data)``: a result reached its sink here (once per new output);
    - ``held_dropped(chain, run, seq, why)``: this node let a held result go, "budget" (the hold
      budget full) or "superseded" (a newer result of a latest-only chain);
    - ``died_with_process(chain, run, seq)``: an output of a chain sourced here died with the
      crashed process (in its memory only) if its sink never gets it: said by the restarted process
      for the seqs it may have had alone (`Resuming._died_with_process`, `_died_in_hand`);
    - ``sink_journal(chain, run, seq)``: an output the crashed sink here had delivered in its last
      commit, named by the restarted one (its recording may have died with the process);
    - ``joined(chain, run, seq)``: a fan-in stage here made its chain's input seq from one join
      step (`autopower.node.joining`): what a source's frame is to a sourced chain.
    """

    output: Callable[[str, int, int, bytes], None] = _ignore
    held_dropped: Callable[[str, int, int, str], None] = _ignore
    died_with_process: Callable[[str, int, int], None] = _ignore
    sink_journal: Callable[[str, int, int], None] = _ignore
    joined: Callable[[str, int, int], None] = _ignore


class SinkListeners:
    """The listeners of one node, told in the order they registered. A listener guards itself
    (the recorder catches its own errors): what one raises reaches the caller, as a bug should."""

    def __init__(self) -> None:
        self._listeners: list[SinkListener] = []

    def add(self, listener: SinkListener) -> None:
        self._listeners.append(listener)

    def __bool__(self) -> bool:  # anyone to tell (an output's data is not copied for nobody)
        return bool(self._listeners)

    def output(self, chain: str, run: int, seq: int, data: bytes) -> None:
        for listener in self._listeners:
            listener.output(chain, run, seq, data)

    def held_dropped(self, chain: str, run: int, seq: int, why: str) -> None:
        for listener in self._listeners:
            listener.held_dropped(chain, run, seq, why)

    def died_with_process(self, chain: str, run: int, seq: int) -> None:
        for listener in self._listeners:
            listener.died_with_process(chain, run, seq)

    def sink_journal(self, chain: str, run: int, seq: int) -> None:
        for listener in self._listeners:
            listener.sink_journal(chain, run, seq)

    def joined(self, chain: str, run: int, seq: int) -> None:
        for listener in self._listeners:
            listener.joined(chain, run, seq)
