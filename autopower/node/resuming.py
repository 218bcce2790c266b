"""Resuming: a restarted process carries on from its crashed one's saved state.

The agent saves `Resuming.state` with every status (`autopower.agent.resume`); a restarted process
gives it to its `NodeRuntime` (`NodeStores.resume_from`), which resumes at the first plan of the same
mission: the battery meter and the sources go on where they were, held results are taken back, and
the outputs that died with the process are named for the recording. A robot restarted while the base
station is out of reach goes on alone with the plan it saved (`saved_plan`).

`Resuming` is a collaborator of `NodeRuntime`. It owns the saved state until it is used, whether the
node resumed, and the time it was down (`NodeStatus.down`).
"""

from __future__ import annotations

import base64
import copy
import logging
import secrets

from autopower.errors import ProtocolError
from autopower.node.meter import BatteryMeter
from autopower.node.ports import SinkListeners
from autopower.protocol import MissionInfo, PlanUpdate, SourceStats, decode

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


def mission_key(mission) -> dict:
    """What identifies one mission (a `MissionInfo`): a restarted process resumes only the same one."""
    return {"scenario": mission.scenario, "epoch_unix": mission.epoch_unix, "speed": mission.speed}
# the wall time a crash can take frames with it: a status period (the sink's commit) and its delay
DIED_WITH_PROCESS_S = 2.0

# A restarted agent goes on alone with the plan it ran (`Resuming.saved_plan`) only if that was
# saved this recently: a crash is restarted within seconds (up's supervisor, systemd's RestartSec);
# an older file is another run's.
RESUME_ALONE_MAX_AGE_S = 300.0


def new_process_id() -> int:
    """A number telling one process of a node from its others (`NodeStatus.process`): a base station
    that lost a robot tells by it whether the robot came back as the same process. Random, not the
    start time: a robot without a real-time clock may start two processes at the same time of day.
    Bit 62 set, so that every process's takes as many bytes on the wire."""
    return 1 << 62 | secrets.randbits(62)


class Resuming:
    """A restarted node's saved state: applied at the mission's first plan, and saved again."""

    def __init__(self, rt, saved: dict | None, listeners: SinkListeners):
        """``rt``: the `NodeRuntime` that resumes; ``saved``: its crashed process's saved state (None:
        a fresh start); ``listeners``: who hears of the outputs that died with that process."""
        self.rt = rt
        self.resume_from = saved
        self._listeners = listeners
        self.resumed = False
        # chain -> the run whose source position was taken from the saved state (`NodeStatus.resumed`)
        self.sources: dict[str, int] = {}
        self.down: tuple[float, float] | None = None  # see NodeStatus.down

    def resume(self, mission: MissionInfo, meter: BatteryMeter) -> BatteryMeter:
        """Carry on from a crashed process's saved state if it belongs to this very mission: the
        mission's new ``meter`` restored from it, which the runtime runs on (the one given, as it was,
        when there is none or it is damaged)."""
        saved, self.resume_from = self.resume_from, None
        if not saved or saved.get("mission") != mission_key(mission) or saved.get("node") != self.rt.node:
            return meter
        fresh = copy.copy(meter)
        try:
            sources = {name: SourceStats(run=int(src["run"]), produced=int(src["seq"]),
                                         missed=int(src.get("missed", 0)), produced_total=int(src["produced_total"]),
                                         missed_stopped=int(src.get("missed_stopped", 0)))
                       for name, src in saved.get("sources", {}).items() if name in self.rt.chains}
            meter.restore(saved)
        except (AttributeError, KeyError, TypeError, ValueError) as exc:  # a damaged file must not crash-loop us
            log.warning("%s: resume state unusable (%s); starting from the mission's energies", self.rt.node, exc)
            return fresh
        self.rt.feeds.resume(sources)
        self.resumed = True
        self.sources = {name: src.run for name, src in sources.items()}
        self.rt.holds.take_back(mission_key(mission))
        self._died_with_process(sources, mission)
        self._died_in_hand(sources, saved.get("in_hand"))
        # what `advance` charges for the time we were down (the robot drew idle current, radios asleep)
        self.down = (meter.t, 0.0 if meter.mains else meter.platform.idle_w + sum(
            self.rt.scenario.radios[m].sleep_w for m in meter.media))
        log.warning("%s: resumed after a restart: battery %.1f J (consumed %.1f J up to t=%.1f s), sources %s",
                    self.rt.node, meter.battery_j if not meter.mains else float("nan"), meter.consumed_j, meter.t,
                    {n: s["seq"] for n, s in saved.get("sources", {}).items()} or "none")
        return meter

    def _died_with_process(self, sources: dict[str, SourceStats], mission: MissionInfo) -> None:
        """Say which outputs of this robot's own chains (source and sink here) died with the crashed process.

        A source notes each seq on disk before its frame leaves (`ResumeFile.note_source`), and the
        sink notes what it delivered with each status (`SinkStore.commit`). A frame between the two
        at the kill (in a stage's queue here, or its output delivered since the last status) existed
        only in the process's memory: the restarted source goes on after it, and the sink never gets
        it. They are logged apart (as a full hold's drops are), so the replay tells what a crash
        costs from what the team lost. Only the
        tail after the last output the sink had committed counts, and only if it is short (a crash
        explains a few periods, not an older gap: longer tails are left to count as lost).
        """
        for name, src in sources.items():
            chain, ledger = self.rt.chains.get(name), self.rt.sinks.get(name)
            if chain is None or chain.source != self.rt.node or chain.sink != self.rt.node or ledger is None \
                    or ledger.run != src.run:
                continue
            first = max(ledger.contiguous, max(ledger.above, default=-1) + 1)
            tail = range(first, src.produced)
            if not tail:
                continue
            if len(tail) > DIED_WITH_PROCESS_S * mission.speed / chain.period_s + 2:
                log.warning("%s: %s seq %d-%d never reached this sink before the restart; more than a crash "
                            "explains: counted as lost", self.rt.node, name, tail[0], tail[-1])
                continue
            self.rt.tally("died-with-process", len(tail))
            log.warning("%s: %s seq %d-%d died with the crashed process (in its memory only)", self.rt.node, name,
                        tail[0], tail[-1])
            for seq in tail:
                self._listeners.died_with_process(name, src.run, seq)

    def _died_in_hand(self, sources: dict[str, SourceStats], in_hand) -> None:
        """Say which outputs of this robot's chains whose sink is elsewhere may have died with the
        crashed process: those its source made from the lowest seq the process still had in hand
        at its last save (`_lowest_in_hand`) on. Each of them was at most in this process's memory
        and on its way: one that reached the next hop is delivered and counts as such (the replay
        counts a seq as died only if no sink got it and no node names it in flight); one that did
        not died with the process. A result the restarted process took back from its hold journal
        did not die. A saved state without the record (an older file) names none."""
        if not isinstance(in_hand, dict):
            return
        taken_back = {(f.chain, f.run, f.seq) for f in self.rt.holds.held.values()}
        for name, src in sources.items():
            saved = in_hand.get(name)
            chain = self.rt.chains.get(name)
            if chain is None or chain.source != self.rt.node or chain.sink == self.rt.node \
                    or not (isinstance(saved, list) and len(saved) == 2 and all(isinstance(v, int) for v in saved)) \
                    or saved[0] != src.run:
                continue
            window = [seq for seq in range(max(saved[1], 0), src.produced) if (name, src.run, seq) not in taken_back]
            if not window:
                continue
            self.rt.tally("maybe-died-with-process", len(window))
            log.warning("%s: %s seq %d-%d were in this robot's hands only or on their way when it crashed: "
                        "those their sink never gets died with the process", self.rt.node, name, window[0], window[-1])
            for seq in window:
                self._listeners.died_with_process(name, src.run, seq)

    def state(self) -> dict | None:
        """What a restarted process needs to carry on (None before the mission starts)."""
        if self.rt.mission is None or self.rt.meter is None:
            return None
        self.rt.metering.settle_relayed()

        meter = self.rt.meter
        sources = {n: {"run": s.run, "seq": s.produced, "missed": s.missed, "produced_total": s.produced_total,
                       "missed_stopped": s.missed_stopped}
                   for n, s in self.rt.feeds.stats().items()}
        return {"node": self.rt.node, "mission": mission_key(self.rt.mission), "t_virtual": meter.t,
                "initial_j": meter.initial_j, "energy_j": dict(meter.energy_j), "cpu_busy_s": meter.cpu_busy_s,
                "runtime_cpu_s": meter.runtime_cpu_s, "airtime_s": dict(meter.airtime_s), "media": sorted(meter.media), "sources": sources,
                "in_hand": self._lowest_in_hand(),
                # the plan we run (a subgroup round's placement included): see `saved_plan`
                "plan": self.rt.plan_view.text(),
                "saved_unix": self.rt.wall()}

    def _lowest_in_hand(self) -> dict[str, list[int]]:
        """Per chain sourced here whose sink is elsewhere: [run, the lowest seq of the source's run
        this process still has in hand]. Custody keeps every frame the chain's source or a stage here
        sent until the next hop has run it, or its sink has it (`custody`): below this seq each one
        was in another node's hands, at or above it, and up to what the source makes next, it may
        be in this process's memory only (`_died_with_process`)."""
        out = {}
        for name, runner in self.rt.sources.items():
            chain = self.rt.chains.get(name)
            if chain is None or chain.sink == self.rt.node:
                continue
            low = runner.seq
            for target in range(len(chain.stages) + 1):
                low = min(low, self.rt.custody.floor(name, target, runner.run, low))
            out[name] = [runner.run, low]
        return out

    def saved_plan(self, max_age_s: float = RESUME_ALONE_MAX_AGE_S) -> PlanUpdate | None:
        """The plan a crashed process of this node ran, from its resume state, if it was saved less
        than ``max_age_s`` ago and is whole (None otherwise: a stale file must not restart an old
        mission). A robot restarted while the base station is out of reach goes on with it
        (`AgentProcess._resume_alone`) instead of idling until the base station returns."""

        saved = self.resume_from
        if not saved or saved.get("node") != self.rt.node or not isinstance(saved.get("plan"), str):
            return None
        try:
            age = self.rt.wall() - float(saved["saved_unix"])
            plan = decode(base64.b64decode(saved["plan"], validate=True), PlanUpdate)
        except (KeyError, TypeError, ValueError, ProtocolError) as exc:  # binascii.Error is a ValueError
            log.warning("%s: the saved plan is unusable (%s); waiting for the base station", self.rt.node, exc)
            return None
        if not 0.0 <= age <= max_age_s or mission_key(plan.mission) != saved.get("mission"):
            return None
        return plan
