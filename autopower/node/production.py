"""Production: this node's sources capture a frame each period and send it to their chain's first stage.

`Production` is a collaborator of `NodeRuntime`. It owns when the node's timer last turned (a node
away longer than a period, stopped or frozen, skips the captures it missed: `Sources.due`) and who is
told when a source advanced (`NodeStores.on_produced`: noted before the frame leaves, so that a crash
never reuses its seq). The sources themselves are `Sources`' (`autopower.node.sources`); a frame
captured goes into custody and on along the data path (`Frames.emit`).
"""

from __future__ import annotations

import logging
from typing import Callable

from autopower.node.guard import ComponentHung
from autopower.node.stages import SourceRunner, pad
from autopower.protocol import ChainFrame

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class Production:
    """The node's captures: each due source's frame, made, checked and sent."""

    def __init__(self, rt, on_produced: Callable[[SourceRunner], None] | None):
        """``rt``: the `NodeRuntime` whose sources these are; ``on_produced``: told of each frame a
        source made, before it leaves."""
        self.rt = rt
        self._on_produced = on_produced
        self._last_turn_wall: float | None = None  # the timer's last turn (a node away a second was stopped)

    def prepare(self) -> None:
        """Build this node's sources before it joins (`Sources.prepare`)."""
        self.rt.feeds.prepare(self.rt.chains.values())

    def tick(self, wall: float) -> None:
        """At the node's timer: a frame from each source whose period is due."""
        now = self.rt.now()
        away_s = wall - self._last_turn_wall if self._last_turn_wall is not None else 0.0
        self._last_turn_wall = wall
        for runner, t_tick in self.rt.feeds.due(now, away_s):
            self._produce(runner, t_tick)

    def _produce(self, runner: SourceRunner, t_tick: float) -> None:
        chain = runner.chain
        if not self.rt.custody.has_room(chain.name, 0, chain.message_bytes[0], self.rt.wall(), sharers=len(self.rt.feeds)):
            # back-pressure: the first stage has not run what this node holds for it (`Custody.has_room`)
            runner.missed += 1
            self.rt.tally("missed-periods")
            self.rt.tally("missed-periods-backlog")
            if self.rt.counters["missed-periods-backlog"] == 1 or self.rt.counters["missed-periods-backlog"] % 100 == 0:
                log.warning("%s: source %s skipped a capture: its consumer has not run the %d frame(s) held for it "
                            "(custody full; %d skipped so far)", self.rt.node, chain.name,
                            self.rt.custody.held_for(chain.name, 0), self.rt.counters["missed-periods-backlog"])
            return
        try:
            data = self.rt.guard.call(runner.source.produce, runner.seq, timeout_s=self.rt.components.hang_limit_s(chain))
            payload = pad(data, chain.message_bytes[0], f"{chain.name} source")
        except ComponentHung as exc:
            self._source_hung(runner, f"produce(seq {runner.seq}): {exc}")
            return
        except Exception as exc:
            self.rt.count("source-error", f"{chain.name}: {exc}", logging.ERROR)
            return
        host = self.rt.plan.placement.get(chain.stages[0].name)
        if host is None:
            self.rt.count("unplaced-stage", f"{chain.stages[0].name} has no host")
            return
        # latency counts from the capture (a frame taken from the sensor's queue waited there)
        waited_s = max(0.0, self.rt.clock.wall() - self.rt.clock.wall_at(t_tick))
        frame = ChainFrame(chain=chain.name, run=runner.run, seq=runner.seq, target=0, t_virtual=t_tick,
                           t_unix=self.rt.wall() - waited_s, payload_len=len(data), payload=payload)
        self.rt.feeds.produced(runner)
        if self._on_produced is not None:  # noted before it leaves: a crash after this never reuses the seq
            self._on_produced(runner)
        self.rt.frames.emit(frame, host)

    def _source_hung(self, runner: SourceRunner, detail: str) -> None:
        """A source that hangs is stopped (one that raises only loses that frame, counted)."""
        chain = runner.chain
        self.rt.feeds.hang(runner)  # not restarted in this run
        self.rt.hosting.source_failed(chain, detail)
