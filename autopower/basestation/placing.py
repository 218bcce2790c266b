"""Placing: closing the gap between the target placement and what nodes confirm, one stage at a time.

Assign a stage with no live host; Prepare -> MigrateOut -> StageReady for a stage that moves;
abort a migration whose ends vanish. Every confirmed change is published as a PlanUpdate.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from dataclasses import dataclass

from autopower.protocol import (
    INBOX_MESSAGES,
    Assign,
    MigrateOut,
    Prepare,
    Prepared,
    Release,
    StageFailed,
    StageReady,
    batched,
    encode,
    unbatch,
)

log = logging.getLogger("autopower.basestation.coordinator")  # one logger for the coordinator's parts
# what a node may report in `StageFailed.what` (anything else is ignored)
STAGE_FAILURES = ("raised", "not-bytes", "oversize", "hung", "export-failed", "import-failed", "source-hung")


@dataclass
class Migration:
    stage: str
    generation: int
    to_node: str
    from_node: str | None  # None: a fresh assignment
    phase: str  # "assigning" | "preparing" | "transferring"
    started_unix: float
    # The order of its phase (Assign, Prepare or MigrateOut), kept encoded to be sent again as it
    # was while unanswered: the order or its answer can be lost with a link that changes under it.
    order: bytes = b""
    order_to: str = ""
    sent_unix: float = 0.0
    resends: int = 0


class Placing:
    """The coordinator's placing part: target placement -> assignments and migrations. Mixed into `Coordinator`, whose state it uses."""

    def set_target(self, target: dict[str, str]) -> None:
        """Where each stage should run (`reconcile` orders what closes the gap)."""
        self.target = target

    def retarget(self, stage: str, node: str) -> None:
        """``stage`` should run on ``node``."""
        self.target[stage] = node

    def generation_above(self, floor: int) -> None:
        """The next generation handed out is above ``floor`` and above every one handed out so far."""
        self.generation = max(self.generation, floor) + 1

    def adopt_team(self, placement: dict[str, str], generation_of: dict[str, int],
                   waiting: dict[str, tuple[str, int]], runs: dict[str, int], unknown: set[str],
                   stale: list[tuple[str, str]]) -> None:
        """A running team taken over: its stages run where they run (``generation_of``: the instance
        each is), those of ``waiting`` still wait for their state, its chains go on with their
        ``runs`` (``unknown``: those whose run a robot has still to say), and ``stale``'s (node,
        stage) copies are released."""
        self.placement = placement
        for stage, (node, generation) in waiting.items():
            # its state is on its way or lost: its StageReady completes it, else the migration
            # timeout restarts it there without (`Coordinator.on_timer`), not a stage starting for good
            self.migrations[stage] = Migration(stage, generation, node, None, "transferring", self.wall())
        self.placed_generation = generation_of
        self.target = dict(placement)
        for chain, run in runs.items():
            self.runs[chain] = run
            self.run_live[chain] = True  # its sequence goes on: a new instance starts where inputs are
        self.runs_unknown |= unknown
        self._update_running()
        for node, stage in stale:
            self._send(node, Release(stage=stage, generation=self._next_generation()))
        self.adopted += len(placement)

    def _next_generation(self) -> int:
        self.generation += 1
        return self.generation

    @contextmanager
    def orders_batched(self):
        """Every order made within goes to its node in one put per node (`Batch`), at the end: a
        plan that places 150 stages on 30 robots is 30 puts (and 30 answers), not 150."""
        if self.control_batch is not None:  # within a batch already: its orders join it
            yield
            return
        self.control_batch = {}
        try:
            yield
        finally:
            batch, self.control_batch = self.control_batch, None
            for node, payloads in batch.items():
                self.send_to(node, self.keys.node_control(node), batched(payloads))

    def reconcile(self) -> None:
        """Order what closes the gap between the target and the placement."""
        with self.orders_batched():
            self._reconcile()

    def _reconcile(self) -> None:
        alive = self.alive_nodes()
        for stage in list(self.placement):
            if stage not in self.target and stage not in self.migrations:
                node = self.placement.pop(stage)
                if node in alive:
                    self._send(node, Release(stage=stage, generation=self._next_generation()))
        for stage, want in self.target.items():
            if stage in self.migrations or self.placement.get(stage) == want or want not in alive:
                continue
            have = self.placement.get(stage)
            chain = self.chain_of[stage]
            if (have is None or have not in alive) and chain.name in self.runs_unknown:
                continue  # a fresh instance needs its chain's run: assigned once the source robot says it
            gen = self._next_generation()
            if have is None or have not in alive:
                self.placement.pop(stage, None)
                run, resume = self._run_for(chain, stage, want)
                m = self.migrations[stage] = Migration(stage, gen, want, None, "assigning", self.wall())
                self._order(m, want, Assign(stage=stage, generation=gen, chain=chain.name, run=run, resume_seq=resume))
            else:
                m = self.migrations[stage] = Migration(stage, gen, want, have, "preparing", self.wall())
                self._order(m, want, Prepare(stage=stage, generation=gen, from_node=have))
        self._update_running()

    def _run_for(self, chain, stage: str, node: str) -> tuple[int, int | None]:
        """The run a fresh instance of ``stage`` (on ``node``) joins, and the seq it starts at.

        A chain that had stopped entirely (disabled, or its only host died) starts a new run at
        seq 0; a stage replacing a dead host in a chain that keeps running continues the run
        from the first input it sees. A new run is said: what the old one still holds upstream
        is obsolete from then on (docs/known-limits.md).
        """
        names = {s.name for s in chain.stages}
        busy = any(s in self.placement or s in self.migrations for s in names)
        if not busy and chain.name not in self.running:
            self.runs[chain.name] = self.runs.get(chain.name, -1) + 1
            self.run_live[chain.name] = False
            if self.runs[chain.name] > 0:  # a restart (its first run is the mission's start)
                self.note(f"{chain.name} starts run {self.runs[chain.name]} with {stage} on {node} (the chain had "
                          f"stopped)")
        return self.runs[chain.name], (None if self.run_live.get(chain.name) else 0)

    def _update_running(self) -> None:
        running = {}
        for chain in self.scenario.chains:
            names = [s.name for s in chain.stages]
            if chain.name in self.runs_unknown:
                continue  # not declared running before its run is known (`Coordinator._learn_runs`)
            if names and all(s in self.target and s in self.placement for s in names):
                running[chain.name] = self.runs[chain.name]
                self.run_live[chain.name] = True
        self.running = running

    def on_inbox(self, payload: bytes) -> None:
        """An answer to an order, as it arrives on the base station's inbox (raises ProtocolError
        for anything else: the caller counts it)."""
        for _, msg in unbatch(payload, INBOX_MESSAGES):  # a node's answers to one batch of orders come in one
            if isinstance(msg, Prepared):
                self.on_prepared(msg)
            elif isinstance(msg, StageReady):
                self.on_stage_ready(msg)
            else:
                self.on_stage_failed(msg)

    def on_prepared(self, msg: Prepared) -> None:
        m = self.migrations.get(msg.stage)
        if m is None or m.generation != msg.generation or m.phase != "preparing" or msg.node != m.to_node:
            return
        m.phase = "transferring"
        m.resends = 0
        self._order(m, m.from_node, MigrateOut(stage=msg.stage, generation=m.generation, to_node=m.to_node))

    def _order(self, m: Migration, node: str, msg) -> None:
        m.order, m.order_to, m.sent_unix = encode(msg), node, self.wall()
        self._send_order(m)

    def _send_order(self, m: Migration) -> None:
        self.send_control(m.order_to, m.order)

    def order_resend_unix(self, m: Migration) -> float:
        """When an unanswered order goes again: after ``migration_resend_s``, then twice as long
        each time (a slow state transfer is not flooded with requests to send it again)."""
        return m.sent_unix + self.config.migration_resend_s * 2 ** min(m.resends, 4)

    def resend_orders(self) -> None:
        """Send again each order still unanswered after its wait.

        A node answers a repeated order without acting twice (`agent.hosting`): a Prepare or an
        Assign it has carried out is answered again, a MigrateOut it has carried out sends the
        same state again, and a state that arrives twice is imported once. So a lost order, a lost
        answer or a lost state costs a resend, not the stage's state and the inputs it held
        (which is what abandoning the migration after ``migration_timeout_s`` costs).
        """
        now = self.wall()
        with self.orders_batched():
            for m in self.migrations.values():
                if m.order and now >= self.order_resend_unix(m) and m.order_to in self.alive_nodes():
                    m.resends += 1
                    self.order_resends += 1
                    m.sent_unix = now
                    log.info("coordinator: %s: no answer to its %s order to %s; sent again (%d)", m.stage, m.phase,
                             m.order_to, m.resends)
                    self._send_order(m)

    def on_stage_ready(self, msg: StageReady) -> None:
        m = self.migrations.get(msg.stage)
        if m is None or m.generation != msg.generation or msg.node != m.to_node:
            return
        del self.migrations[msg.stage]
        self.placement[msg.stage] = msg.node
        self.placed_generation[msg.stage] = m.generation
        if m.from_node is None:
            self.assignments_done += 1
        else:
            self.migrations_done += 1
            self.downtimes_ms.append(msg.downtime_ms)
            self.migration_log.append({"stage": msg.stage, "from": m.from_node, "to": msg.node,
                                       "downtime_ms": msg.downtime_ms, "held_inputs": msg.buffered,
                                       "total_ms": (self.wall() - m.started_unix) * 1e3})
            log.info("coordinator: %s moved %s -> %s in %.1f ms (%d inputs held)", msg.stage, m.from_node,
                     msg.node, msg.downtime_ms, msg.buffered)
        self.reconcile()
        self.plans.mark_due()  # `Coordinator.on_timer` publishes it, once for every stage ready meanwhile (plan_batch_s)

    def on_stage_failed(self, msg: StageFailed) -> None:
        """A node stopped a stage's component, or refused to migrate it (see `StageFailed`).

        A refused migration (``running``): the migration is abandoned, the stage stays where it
        runs and is pinned there (moving it again would fail the same way). A stopped component:
        its chain is stopped, as ``autopower chain --disable`` would, and the policy re-plans the
        rest; enabling the chain again restarts it with a fresh instance. A state that imported on
        its old host but not on the new one: the new host runs it without, `StageReady` follows.
        """
        chain = self.chain_of.get(msg.stage)
        if chain is None or msg.what not in STAGE_FAILURES:
            return
        m = self.migrations.get(msg.stage)
        current = m is not None and m.generation == msg.generation
        why = f"{msg.what}: {msg.detail[:300]}"  # a network message: bounded before it is kept
        if msg.running:
            if not current or msg.node != m.from_node:  # the new host runs it without its state
                self.note(f"{msg.stage} on {msg.node}: {why}")
                return
            del self.migrations[msg.stage]
            self.aborted += 1
            if m.to_node in self.alive_nodes():
                self._send(m.to_node, Release(stage=msg.stage, generation=self._next_generation()))
            self.operating.pin(msg.stage, msg.node)
            self.target[msg.stage] = msg.node
            self.note(f"{msg.stage}: migration {msg.node} -> {m.to_node} refused ({why}); it keeps running on "
                      f"{msg.node}, pinned there")
            self._predict()
            self.reconcile()
            self.plans.publish_plan()
            return
        if msg.what == "source-hung":
            if msg.node != chain.source:
                return
        elif current and msg.node == m.to_node:
            del self.migrations[msg.stage]  # a fresh instance that failed to start
        elif self.placement.get(msg.stage) != msg.node:
            return  # about an instance that is gone already
        if not self.operating.stage_failed(msg.stage, f"{msg.node}: {why}", chain.name):
            return
        self._event("chain-disable", chains=(chain.name,))
        self.note(f"{msg.stage} failed on {msg.node} ({why}); chain {chain.name} stopped (enable it to restart)")
        self.replan(f"{msg.stage} failed")

    def _abort(self, stage: str, why: str, *, restart_at_target: bool = False) -> None:
        """Give a migration up: its ends release the stage, which restarts without its state.

        ``restart_at_target``: the caller reconciles at once and the target is still the new
        host, so that host is not told to release: the Assign that follows replaces its waiting
        instance and keeps the inputs it holds (acknowledged to their producers: nobody else has them).
        """
        m = self.migrations.pop(stage)
        self.aborted += 1
        self.note(f"{stage}: {m.phase} to {m.to_node} abandoned ({why}); restarting it without state")
        gen = self._next_generation()
        keep = m.to_node if restart_at_target and self.target.get(stage) == m.to_node else None
        for node in sorted({m.to_node, m.from_node} - {None, keep}):
            if node in self.alive_nodes():
                self._send(node, Release(stage=stage, generation=gen))
        self.placement.pop(stage, None)
