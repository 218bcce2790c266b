"""Components: building the stages' components, in this process or in worker processes of their own.

`Components` is a collaborator of `NodeRuntime`. It owns the factories of the scenario's components
and sources, whether stages run in worker processes (`autopower.node.workers`), the zygote that
forks them and how a worker's result wakes the owning process; it builds an instance (a variant's
parameters, a fan-in stage's join around it), checks a state before it is shipped, imports one, and
finishes the runs whose results come back from the workers. A run's output goes on along the data
path (`Frames`); a component that misbehaves fails its stage (`Hosting.fail_stage`).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from autopower.model.scenario import Chain, Stage
from autopower.model.variants import runtime_component
from autopower.node.guard import hang_limit_s
from autopower.node.stages import HostedStage, Lifecycle, chain_seed
from autopower.node.workers import (
    NotBytes,
    StageWorker,
    WorkerComponent,
    WorkerCrashed,
    Zygote,
    recipe_for,
    worker_of,
)
from autopower.protocol import ChainFrame

log = logging.getLogger("autopower.node.runtime")  # one logger for the node's parts


class Components:
    """The node's stage components and their worker processes."""

    def __init__(self, rt, *, make_component: Callable, make_source: Callable, stage_workers: bool,
                 notify_work: Callable[[], None] | None):
        """``rt``: the `NodeRuntime` whose stages these run. ``stage_workers``: each stage's component in
        a worker process of its own, called asynchronously; ``notify_work``: how a worker's result
        wakes the owning process's loop (without it results are collected at the next timer tick)."""
        self.rt = rt
        self._make_component = make_component
        self._make_source = make_source
        self.stage_workers = stage_workers
        self._notify_work = notify_work
        self._zygote = None
        if stage_workers:  # started now, off the loop (`Zygote.prestart`)
            self._zygote = Zygote()
            self._zygote.prestart()

    @property
    def has_workers(self) -> bool:
        """Whether stages may run in worker processes here (their results are collected at each tick)."""
        return self._zygote is not None

    def source_key(self, chain: Chain) -> tuple[str, str, int]:
        """What builds ``chain``'s source: its first stage's component, the robot and the chain's seed."""
        return chain.stages[0].component, chain.source, chain_seed(self.rt.scenario, chain)

    def build_source(self, component: str, robot: str, seed: int):
        """A new source of a chain (`autopower.node.sources`)."""
        return self.build(self._make_source, component, robot, seed)

    def new_component(self, chain: Chain, stage: Stage):
        return self.rt.flows.wrap(self._instance(chain, stage), stage.name,
                               self.rt.wall)  # a fan-in stage's join travels with its state

    def _instance(self, chain: Chain, stage: Stage):
        """A new instance of the stage's component: in a worker process of its own with
        ``stage_workers`` (`agent.workers`), when the worker can build it; else in this process."""
        seed = chain_seed(self.rt.scenario, chain)
        if self.stage_workers:
            kind, parameters = runtime_component(self.rt.scenario, stage.component)
            recipe = recipe_for(self._make_component, kind, chain.source, seed, parameters)
            if recipe is None:
                self.rt.tally("stage-in-process")  # a factory a worker cannot import: runs here as before
            else:
                if self._zygote is None:
                    self._zygote = Zygote()
                try:
                    worker = StageWorker(self._zygote, self._notify_work)
                except (OSError, WorkerCrashed) as exc:  # no worker to be had: the stage still runs, here
                    self.rt.count("stage-worker-unavailable", f"{stage.name}: {exc}", logging.ERROR)
                else:
                    try:
                        return WorkerComponent(worker, recipe, self.hang_limit_s(chain))
                    except BaseException:
                        worker.kill()
                        raise
        return self.build(self._make_component, stage.component, chain.source, seed)

    def build(self, factory, component: str, robot: str, seed: int):
        """A component or source of a stage's component (a variant's: with its parameters)."""
        kind, parameters = runtime_component(self.rt.scenario, component)
        args = (kind, robot, seed, parameters) if parameters else (kind, robot, seed)
        return self.rt.guard.counted(factory, *args)

    def exportable_state(self, hosted: HostedStage) -> bytes | tuple[str, str]:
        """The state to ship, checked to import into a fresh instance; or (what, why) it cannot move.

        The check runs here, before this node gives its instance up: a state that does not import
        (a bug in ``import_state``, a format change) refuses the migration and the stage keeps
        running where it was. The new host runs the same code, so it imports there too; if it
        still fails there (different code installed), that host starts it without the state from
        where it stopped (no input lost or repeated) and says so.
        """
        component, chain, limit = hosted.component, hosted.chain, self.hang_limit_s(hosted.chain)
        if not callable(getattr(component, "export_state", None)):
            return b""  # a stateless component: restarted fresh on its new host
        try:
            state = self.rt.guard.call(component.export_state, timeout_s=limit)
        except Exception as exc:
            return "export-failed", f"export_state: {type(exc).__name__}: {exc}"
        if not isinstance(state, bytes):
            return "export-failed", f"export_state returned {type(state).__name__}, not bytes"
        probe = None
        try:
            probe = self.new_component(chain, hosted.stage)
            self.rt.guard.call(probe.import_state, state, timeout_s=limit)
        except Exception as exc:
            return "import-failed", f"import_state: {type(exc).__name__}: {exc}"
        finally:
            self.retire(probe)
        return state

    def import_state(self, component, state: bytes, chain: Chain) -> None:
        if state or callable(getattr(component, "import_state", None)):
            self.rt.guard.call(component.import_state, state, timeout_s=self.hang_limit_s(chain))

    def hang_limit_s(self, chain: Chain) -> float:
        return hang_limit_s(chain.period_s, self.rt.mission.speed if self.rt.mission else 1.0)

    @staticmethod
    def retire(component) -> None:
        """An instance this node gives up: its worker process (if any) is killed at once."""
        worker = worker_of(component)
        if worker is not None:
            worker.kill()

    def collect_results(self) -> None:
        """Finish the runs whose results came back from their workers (the loop, on a nudge or a tick)."""
        for hosted in list(self.rt.hosted.values()):
            worker = worker_of(hosted.component)
            while worker is not None and worker is worker_of(hosted.component):
                done = worker.poll()
                if done is None:
                    break
                (owner, frame), reply = done
                self._finish_remote(owner, frame, reply, worker)

    def _finish_remote(self, hosted: HostedStage, frame: ChainFrame, reply: list | None, worker) -> None:
        if hosted.lifecycle is Lifecycle.FAILED or worker is not worker_of(hosted.component):
            return  # stopped or replaced meanwhile: its result is no longer anyone's
        if reply is None:
            self.rt.hosting.fail_stage(hosted, "crashed", f"run(seq {frame.seq}): its worker process ended "
                            f"({worker.exit_text()})")
        elif reply[0] == "err":
            self.rt.hosting.fail_stage(hosted, "raised", f"run(seq {frame.seq}): {reply[1]}: {reply[2] if len(reply) > 2 else ''}")
        elif reply[0] == "ok" and len(reply) == 3 and isinstance(reply[1], float):  # ["ok", compute s, output]
            self.rt.frames.ran(hosted, frame, reply[2], reply[1])
        else:  # ["bad", type name]: not bytes
            self.rt.frames.ran(hosted, frame, NotBytes(reply[-1]) if reply[0] == "bad" else reply, 0.0)

    def check_workers(self) -> None:
        """Kill the worker of a run that hung (`guard.py`'s rule); its stage has failed."""
        now = time.monotonic()
        for hosted in list(self.rt.hosted.values()):
            worker = worker_of(hosted.component)
            if worker is None or worker.inflight is None:
                continue
            verdict = worker.run_hung(self.hang_limit_s(hosted.chain), now)
            if verdict is not None:
                seq = worker.inflight[0][1].seq
                worker.kill()
                self.rt.hosting.fail_stage(hosted, "hung", f"run(seq {seq}): {verdict}; its worker process was killed")

    def drain(self, hosted: HostedStage) -> bool:
        """Wait (on the loop) until a stage's worker has run every input handed to it; False if the
        stage failed meanwhile."""
        worker = worker_of(hosted.component)
        limit = self.hang_limit_s(hosted.chain)
        while worker is not None and worker.inflight is not None:
            done = worker.poll(0.05)
            if done is not None:
                (owner, frame), reply = done
                self._finish_remote(owner, frame, reply, worker)
                continue
            verdict = worker.run_hung(limit, time.monotonic())
            if verdict is not None:
                seq = worker.inflight[0][1].seq
                worker.kill()
                self.rt.hosting.fail_stage(hosted, "hung", f"run(seq {seq}): {verdict}; its worker process was killed")
        return hosted.lifecycle is not Lifecycle.FAILED

    def close(self) -> None:
        """Kill every stage worker and the zygote (the node is stopping)."""
        for hosted in self.rt.hosted.values():
            self.retire(hosted.component)
        if self._zygote is not None:
            self._zygote.close()
            self._zygote = None
