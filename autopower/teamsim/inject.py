"""Carrying out a fault schedule on a simulated team: each fault starts and ends at its time.

Faults overlap freely. A link direction is cut while any fault cuts it, and loses, duplicates or
delays what the strongest active fault says. A crash of a process already down, or a freeze of
one down, does nothing; a crash ends a freeze. An operator's command that the base station cannot
take (down, frozen, no mission yet) fails, as the operator's query would; the enable that ends a
chain toggle is tried again every second until the base station takes it.
"""

from __future__ import annotations

from autopower.protocol import ChainCommand, MigrateCommand
from autopower.teamsim.faults import Fault

LINK_KINDS = {"cut": "cut", "cut-one-way": "cut", "partition": "cut", "loss": "loss", "duplicate": "dup",
              "reorder": "jitter_s", "roam": "cut", "rate": "rate", "flap": "cut"}
RETRY_S = 1.0


class Injector:
    """Schedules every fault of ``faults`` on ``world`` (the run's `autopower.teamsim.team.World`)."""

    def __init__(self, world, faults: list[Fault]):
        self.world = world
        self.faults = list(faults)
        self.mods: dict[tuple[str, str], dict[int, tuple[str, float]]] = {}  # direction -> fault -> (what, value)
        self.kbps: dict[tuple[str, str], float] = {}  # a direction's medium rate, before any `rate` fault
        self.crashed_by: dict[str, int] = {}
        self.frozen_by: dict[str, set[int]] = {}
        s = world.scheduler
        for i, f in enumerate(self.faults):
            s.at(f.t, self.begin, i)
            if f.duration > 0 and f.kind != "migrate":
                s.at(f.end, self.finish, i)

    # ---- links ------------------------------------------------------------------------------------
    def _directions(self, f: Fault) -> list[tuple[str, str]]:
        net = self.world.network
        if f.kind == "cut-one-way":
            return [(f.a, f.b)]
        if f.kind == "partition":
            side = set(f.nodes)
            return sorted(d for d in net.directions if (d[0] in side) != (d[1] in side))
        return [(f.a, f.b), (f.b, f.a)]

    def _apply(self, direction: tuple[str, str]) -> None:
        net = self.world.network
        d = net.direction(*direction)
        active = self.mods.get(direction, {}).values()
        d.loss = max((v for what, v in active if what == "loss"), default=0.0)
        d.dup = max((v for what, v in active if what == "dup"), default=0.0)
        d.jitter_s = max((v for what, v in active if what == "jitter_s"), default=0.0)
        medium = self.kbps.setdefault(direction, d.kbps)
        net.set_rate(*direction, medium * min((v for what, v in active if what == "rate"), default=1.0))
        net.set_cut(*direction, any(what == "cut" for what, _ in active))

    # ---- start and end ------------------------------------------------------------------------------
    def begin(self, i: int) -> None:
        w, f = self.world, self.faults[i]
        w.trace.note(w.scheduler.now, f"fault {i} begins: {f.describe()}")
        if f.kind in LINK_KINDS:
            what = LINK_KINDS[f.kind]
            for direction in self._directions(f):
                self.mods.setdefault(direction, {})[i] = (what, 1.0 if what == "cut" else f.p)
                self._apply(direction)
            if f.kind == "flap" and f.t + f.p < f.end:
                w.scheduler.at(f.t + f.p, self._flap, i, False)
        elif f.kind in ("crash", "basestation-crash"):
            node = f.a or w.scenario.basestation
            if w.is_up(node) and node not in self.crashed_by:
                self.crashed_by[node] = i
                self.frozen_by.pop(node, None)
                w.crash(node)
        elif f.kind == "freeze":
            if w.is_up(f.a):
                frozen = self.frozen_by.setdefault(f.a, set())
                if not frozen:
                    w.freeze(f.a)
                frozen.add(i)
        elif f.kind == "migrate":
            w.operator(MigrateCommand(stage=f.a, to_node=f.b))
        elif f.kind == "toggle":
            w.ledger.operator_stop(f.a, f.t, f.end)
            w.operator(ChainCommand(chain=f.a, enabled=False))

    def finish(self, i: int) -> None:
        w, f = self.world, self.faults[i]
        w.trace.note(w.scheduler.now, f"fault {i} ends: {f.describe()}")
        if f.kind in LINK_KINDS:
            for direction in self._directions(f):
                self.mods.get(direction, {}).pop(i, None)
                self._apply(direction)
        elif f.kind in ("crash", "basestation-crash"):
            node = f.a or w.scenario.basestation
            if self.crashed_by.get(node) == i:
                del self.crashed_by[node]
                w.restart(node)
        elif f.kind == "freeze":
            frozen = self.frozen_by.get(f.a)
            if frozen is not None and i in frozen:
                frozen.discard(i)
                if not frozen:
                    del self.frozen_by[f.a]
                    w.thaw(f.a)
        elif f.kind == "toggle":
            self._enable(f.a)

    def _flap(self, i: int, down: bool) -> None:
        """A flapping link's next phase (down, or up), every ``p`` seconds until the fault ends."""
        w, f = self.world, self.faults[i]
        w.trace.note(w.scheduler.now, f"fault {i} flaps {'down' if down else 'up'}")
        for direction in self._directions(f):
            if down:
                self.mods.setdefault(direction, {})[i] = ("cut", 1.0)
            else:
                self.mods.get(direction, {}).pop(i, None)
            self._apply(direction)
        if w.scheduler.now + f.p < f.end:
            w.scheduler.at(w.scheduler.now + f.p, self._flap, i, not down)

    def _enable(self, chain: str) -> None:
        w = self.world
        reply = w.operator(ChainCommand(chain=chain, enabled=True))
        if reply is None or not reply.ok:
            w.scheduler.after(RETRY_S, self._enable, chain)
