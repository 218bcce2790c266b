"""Placing: closing the gap between the target placement and what nodes confirm, one stage at a time.

Assign a stage with no live host; Prepare -> MigrateOut -> StageReady for a stage that moves;
abort a migration whose ends vanish. Every confirmed change is published as a PlanUpdate
(`publishing.PlanPublisher`).

`Placement` owns the *desired* placement (``target``: the policy's allocation with the operator's
pins, set by the deciding part through `set_target`) and the *confirmed* one (``placement``: what
nodes acknowledged), the migrations under way, the generations it hands out, the chains' runs
(`runs.ChainRuns`) and the counts of what it did.
"""

from __future__ import annotations

import logging
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable

from autopower.basestation.runs import ChainRuns
from autopower.protocol import (
    INBOX_MESSAGES,
    Assign,
    MigrateOut,
    NodeStatus,
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


class Generations:
    """The generations the base station hands out to stage instances (every order names one; a node
    ignores an order below the instance it runs as stale)."""

    def __init__(self, wall: Callable[[], float]):
        self._wall = wall
        self.last = 0  # the newest handed out or followed
        self._far: set[str] = set()  # robots that reported a generation too far ahead (warned)

    def next(self) -> int:
        self.last += 1
        return self.last

    def above(self, floor: int) -> None:
        """The next generation handed out is above ``floor`` and above every one handed out so far."""
        self.last = max(self.last, floor) + 1

    def at_least(self, floor: int) -> None:
        self.last = max(self.last, floor)

    def follow(self, status: NodeStatus) -> None:
        """Hand out generations above every instance a robot reports hosting.

        Robots start instances without us (subgroup rounds, a robot restarted alone) with
        time-based generations, far above our counter; an instance restarted on the host the plan
        already names keeps its generation, and a robot ignores every order below it as stale (and
        its producers the reports of an instance placed below it). A generation more than a day
        ahead of our clock is not taken (a robot's clock or message gone wrong).
        """
        top = max(status.generations.values(), default=0)
        if top > self.last:
            if top <= int(self._wall() * 1000) + 86_400_000:
                self.last = top
            elif status.node not in self._far:
                self._far.add(status.node)  # said once: it comes with every status
                log.warning("coordinator: %s reports a stage generation %d, more than a day ahead of this "
                            "clock; not followed (check the robot's clock)", status.node, top)


class Placement:
    """The coordinator's placing part: target placement -> assignments and migrations, and what nodes confirm."""

    def __init__(self, team):
        """``team``: the `Coordinator` that says who is alive and sends the orders (``send_to``)."""
        self.team = team
        self.placement: dict[str, str] = {}
        # the generation of the instance `placement` names (what a returning robot's is compared with)
        self.placed_generation: dict[str, int] = {}
        self.target: dict[str, str] = {}
        self.migrations: dict[str, Migration] = {}
        # orders made while a reconcile runs, per node: sent as one put each when it ends (`reconcile`)
        self.control_batch: dict[str, list[bytes]] | None = None
        self.generations = Generations(team.wall)  # the generations handed out to stage instances
        self.runs = ChainRuns()  # the chains' runs, and which chains run
        self.downtimes_ms: list[float] = []
        self.migration_log: deque[dict] = deque(maxlen=200)
        self.migrations_done = 0
        self.assignments_done = 0
        self.aborted = 0
        self.order_resends = 0  # migration orders sent again for want of an answer (`resend_orders`)
        self.adopted = 0  # stages taken as placed where a robot runs them (a takeover, a returning robot)
        # source robots whose chains wait to be assigned until their process says whether it holds the run
        self.waiting_for: set[str] = set()

    def set_target(self, target: dict[str, str]) -> None:
        """Where each stage should run (`reconcile` orders what closes the gap)."""
        self.target = target

    def retarget(self, stage: str, node: str) -> None:
        """``stage`` should run on ``node``."""
        self.target[stage] = node

    def adopt_team(self, placement: dict[str, str], generation_of: dict[str, int],
                   waiting: dict[str, tuple[str, int]], runs: dict[str, int], unknown: set[str],
                   stale: list[tuple[str, str]],
                   holders: dict[str, tuple[int | None, int | None]] | None = None) -> None:
        """A running team taken over: its stages run where they run (``generation_of``: the instance
        each is), those of ``waiting`` still wait for their state, its chains go on with their
        ``runs`` (``unknown``: those whose run a robot has still to say; ``holders``: the sighting of a
        chain's source robot and the process that said its run), and ``stale``'s (node, stage) copies are released."""
        self.placement = placement
        for stage, (node, generation) in waiting.items():
            # its state is on its way or lost: its StageReady completes it, else the migration
            # timeout restarts it there without (`time_out`), not a stage starting for good
            self.migrations[stage] = Migration(stage, generation, node, None, "transferring", self.team.wall())
        self.placed_generation = generation_of
        self.target = dict(placement)
        self.runs.adopt(runs, unknown, holders)
        self._update_running()
        for node, stage in stale:
            self.send(node, Release(stage=stage, generation=self.generations.next()))
        self.adopted += len(placement)

    def learn_runs(self, status: NodeStatus) -> None:
        """The runs a takeover did not know, from a status of their source (or a fan-in chain's sink):
        the stages waiting for them are assigned, and the plan says so."""
        if not self.runs.runs_unknown:
            return
        learned = self.runs.learn(status, self.team.scenario.chain, self.team.source_sight)
        if learned:
            self.team.note(f"learned from {status.node}: {', '.join(learned)}")
            self.reconcile()
            self.team.plans.publish_plan()

    def adopt_actual(self, status: NodeStatus, returning: bool = True) -> bool:
        """Take the stages a returning robot runs as placed there, when its instance is the newest.

        Instances are ordered by generation everywhere: a robot stops its instance when it sees a
        newer one running on a peer (`Hosting.yield_to_newer`), and producers' custody follows the
        newest instance's reports (`Custody.on_report`). So a returning robot's instance is adopted
        (and our stale copy released) only when its generation is above the one running where the
        placement says; an older one is released instead. Adopting the older one left the stage
        running nowhere (its robot yielded to ours, which we had released) or, when the robot kept
        it, with producers ignoring its acknowledgements for good.

        A robot that never left (not ``returning``) has a stage adopted only where it runs on two
        nodes at once: one we placed elsewhere, not one we stopped (a release still on its way).
        True when a stage was adopted.
        """
        alive = self.team.alive_nodes()
        adopted = False
        for stage, state in sorted(status.hosted.items()):
            if state != "running" or stage not in self.team.chain_of:
                continue
            theirs = status.generations.get(stage, 0)
            m = self.migrations.get(stage)
            if m is not None:
                if m.to_node != status.node or theirs <= m.generation:
                    continue
                # the robot we were moving it to runs a newer instance already (a round it made while
                # it took us for gone): our order is moot, and it would be refused as stale for good
                del self.migrations[stage]
                self.team.note(f"{stage}: {m.phase} to {m.to_node} overtaken by the instance it started itself")
            previous = self.placement.get(stage)
            if previous == status.node or (not returning and (previous is None or previous not in alive)):
                continue
            ours = self.placed_generation.get(stage) if previous in alive else None
            if ours is not None and ours >= theirs:
                if ours > theirs:
                    self.team.note(f"{stage} still runs on {status.node} as an older instance (generation {theirs}, "
                              f"{previous}'s is {ours}); released there")
                    self.send(status.node, Release(stage=stage, generation=theirs))
                continue
            # generations handed out without us are time-based: jump past them
            self.generations.at_least(int(self.team.wall() * 1000) + 1)
            self.placement[stage] = status.node
            self.placed_generation[stage] = theirs
            if stage not in self.target:
                # its chain had stopped in the plan in force (the robot was away): it runs again, and
                # where it runs is the target until the policy's next answer. Left out, the next
                # reconcile released it, the policy saw it "not running" and placed it afresh in a
                # new run, and what its old run held upstream was obsolete
                self.target[stage] = status.node
            self.adopted += 1
            self.team.note(f"{stage} runs on {status.node} (agreed without the base station); adopted")
            adopted = True
            if previous is not None and previous in alive:
                self.send(previous, Release(stage=stage, generation=self.generations.next()))
        return adopted

    def send(self, node: str, msg) -> None:
        self.send_control(node, encode(msg))

    def send_control(self, node: str, payload: bytes) -> None:
        """An order to ``node``: at once, or with the others of the reconcile that makes it."""
        if self.control_batch is not None:
            self.control_batch.setdefault(node, []).append(payload)
        else:
            self.team.send_to(node, self.team.keys.node_control(node), payload)

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
                self.team.send_to(node, self.team.keys.node_control(node), batched(payloads))

    def reconcile(self) -> None:
        """Order what closes the gap between the target and the placement."""
        with self.orders_batched():
            self._reconcile()

    def _reconcile(self) -> None:
        alive = self.team.alive_nodes()
        for stage in list(self.placement):
            if stage not in self.target and stage not in self.migrations:
                node = self.placement.pop(stage)
                if node in alive:
                    self.send(node, Release(stage=stage, generation=self.generations.next()))
        for stage, want in self.target.items():
            if stage in self.migrations or self.placement.get(stage) == want or want not in alive:
                continue
            have = self.placement.get(stage)
            chain = self.team.chain_of[stage]
            if (have is None or have not in alive) and chain.name in self.runs.runs_unknown:
                continue  # a fresh instance needs its chain's run: assigned once the source robot says it
            if have is None or have not in alive:
                self.placement.pop(stage, None)
                busy = any(s.name in self.placement or s.name in self.migrations for s in chain.stages)
                run, resume, how = self.runs.run_for(chain, busy, self.team.source_sight(chain.source))
                if how == "waiting":  # the run goes on only if the source's process holds it: assigned once it says
                    self.waiting_for.add(chain.source)
                    continue
                # a new run is said: what the old one still holds upstream is obsolete (docs/known-limits.md)
                if how in ("new", "restarted"):
                    why = ("its source robot's process does not hold the run's position" if how == "restarted"
                           else "the operator or a failed component had stopped the chain" if chain.sourced
                           else "a chain with no source starts over")
                    self.team.note(f"{chain.name} starts run {run} with {stage} on {want} ({why})")
                elif how == "resumed":  # its instances start from the oldest input their producer holds
                    self.team.note(f"{chain.name} resumes run {run} with {stage} on {want} (the chain had stopped)")
                gen = self.generations.next()
                m = self.migrations[stage] = Migration(stage, gen, want, None, "assigning", self.team.wall())
                self._order(m, want, Assign(stage=stage, generation=gen, chain=chain.name, run=run, resume_seq=resume))
            else:
                gen = self.generations.next()
                m = self.migrations[stage] = Migration(stage, gen, want, have, "preparing", self.team.wall())
                self._order(m, want, Prepare(stage=stage, generation=gen, from_node=have))
        self._update_running()

    def _update_running(self) -> None:
        self.runs.update(self.team.scenario.chains, self.target, self.placement, self.team.operating.disabled,
                         self.team.source_sight)

    def source_heard(self, status: NodeStatus) -> None:
        """A status of a robot whose chains wait for their source to say whether it holds their run
        (`ChainRuns.run_for`): they are assigned now, if it says enough, and the plan says so."""
        if status.node in self.waiting_for and self.team.source_sight(status.node).current:
            self.waiting_for.discard(status.node)
            ordered = set(self.migrations)
            self.reconcile()
            if set(self.migrations) != ordered:  # (a chain no longer targeted waits for nothing)
                self.team.plans.publish_plan()

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
        m.order, m.order_to, m.sent_unix = encode(msg), node, self.team.wall()
        self._send_order(m)

    def _send_order(self, m: Migration) -> None:
        self.send_control(m.order_to, m.order)

    def order_resend_unix(self, m: Migration) -> float:
        """When an unanswered order goes again: after ``migration_resend_s``, then twice as long
        each time (a slow state transfer is not flooded with requests to send it again)."""
        return m.sent_unix + self.team.config.migration_resend_s * 2 ** min(m.resends, 4)

    def resend_orders(self) -> None:
        """Send again each order still unanswered after its wait.

        A node answers a repeated order without acting twice (`agent.hosting`): a Prepare or an
        Assign it has carried out is answered again, a MigrateOut it has carried out sends the
        same state again, and a state that arrives twice is imported once. So a lost order, a lost
        answer or a lost state costs a resend, not the stage's state and the inputs it held
        (which is what abandoning the migration after ``migration_timeout_s`` costs).
        """
        now = self.team.wall()
        with self.orders_batched():
            for m in self.migrations.values():
                if m.order and now >= self.order_resend_unix(m) and m.order_to in self.team.alive_nodes():
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
                                       "total_ms": (self.team.wall() - m.started_unix) * 1e3})
            log.info("coordinator: %s moved %s -> %s in %.1f ms (%d inputs held)", msg.stage, m.from_node,
                     msg.node, msg.downtime_ms, msg.buffered)
        self.reconcile()
        self.team.plans.mark_due()  # the next timer publishes it, once for every stage ready meanwhile (plan_batch_s)

    def on_stage_failed(self, msg: StageFailed) -> None:
        """A node stopped a stage's component, or refused to migrate it (see `StageFailed`).

        A refused migration (``running``): the migration is abandoned, the stage stays where it
        runs and is pinned there (moving it again would fail the same way). A stopped component:
        its chain is stopped, as ``autopower chain --disable`` would, and the policy re-plans the
        rest; enabling the chain again restarts it with a fresh instance. A state that imported on
        its old host but not on the new one: the new host runs it without, `StageReady` follows.
        """
        chain = self.team.chain_of.get(msg.stage)
        if chain is None or msg.what not in STAGE_FAILURES:
            return
        m = self.migrations.get(msg.stage)
        current = m is not None and m.generation == msg.generation
        why = f"{msg.what}: {msg.detail[:300]}"  # a network message: bounded before it is kept
        if msg.running:
            if not current or msg.node != m.from_node:  # the new host runs it without its state
                self.team.note(f"{msg.stage} on {msg.node}: {why}")
                return
            del self.migrations[msg.stage]
            self.aborted += 1
            if m.to_node in self.team.alive_nodes():
                self.send(m.to_node, Release(stage=msg.stage, generation=self.generations.next()))
            self.team.operating.pin(msg.stage, msg.node)
            self.target[msg.stage] = msg.node
            self.team.note(f"{msg.stage}: migration {msg.node} -> {m.to_node} refused ({why}); it keeps running on "
                      f"{msg.node}, pinned there")
            self.team.prediction.predict()
            self.reconcile()
            self.team.plans.publish_plan()
            return
        if msg.what == "source-hung":
            if msg.node != chain.source:
                return
        elif current and msg.node == m.to_node:
            del self.migrations[msg.stage]  # a fresh instance that failed to start
        elif self.placement.get(msg.stage) != msg.node:
            return  # about an instance that is gone already
        if not self.team.operating.stage_failed(msg.stage, f"{msg.node}: {why}", chain.name):
            return
        self.team.deciding.event("chain-disable", chains=(chain.name,))
        self.team.note(f"{msg.stage} failed on {msg.node} ({why}); chain {chain.name} stopped (enable it to restart)")
        self.team.deciding.replan(f"{msg.stage} failed")

    def abort(self, stage: str, why: str, *, restart_at_target: bool = False) -> None:
        """Give a migration up: its ends release the stage, which restarts without its state.

        ``restart_at_target``: the caller reconciles at once and the target is still the new
        host, so that host is not told to release: the Assign that follows replaces its waiting
        instance and keeps the inputs it holds (acknowledged to their producers: nobody else has them).
        """
        m = self.migrations.pop(stage)
        self.aborted += 1
        self.team.note(f"{stage}: {m.phase} to {m.to_node} abandoned ({why}); restarting it without state")
        gen = self.generations.next()
        keep = m.to_node if restart_at_target and self.target.get(stage) == m.to_node else None
        for node in sorted({m.to_node, m.from_node} - {None, keep}):
            if node in self.team.alive_nodes():
                self.send(node, Release(stage=stage, generation=gen))
        self.placement.pop(stage, None)

    def node_lost(self, node: str) -> None:
        """``node`` left or ran out: what moved to or from it is given up, and nothing runs there."""
        for stage, m in list(self.migrations.items()):
            if node in (m.to_node, m.from_node):
                self.abort(stage, f"{node} left")
        for stage, host in list(self.placement.items()):
            if host == node:
                del self.placement[stage]
        self._update_running()

    def time_out(self, now_wall: float) -> None:
        """Abandon each migration with no answer within ``migration_timeout_s``: it restarts, without its state."""
        timeout = self.team.config.migration_timeout_s
        for stage, m in list(self.migrations.items()):
            if now_wall - m.started_unix > timeout:
                self.abort(stage, f"no answer in {timeout:g} s", restart_at_target=True)
                self.reconcile()
                self.team.plans.publish_plan()

    def deadlines(self) -> list[float]:
        """When a migration times out, and when an unanswered order goes again."""
        deadlines = [m.started_unix + self.team.config.migration_timeout_s for m in self.migrations.values()]
        deadlines += [self.order_resend_unix(m) for m in self.migrations.values() if m.order]
        return deadlines
