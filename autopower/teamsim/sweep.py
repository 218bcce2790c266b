"""Many seeds at once: each drawn, run and judged on its own, spread over worker processes.

What CI's sweep and the benchmark run. A seed's verdict says how to run it again alone.
"""

from __future__ import annotations

import logging
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from autopower.teamsim.faults import KINDS, draw
from autopower.teamsim.team import SimConfig, run


@dataclass(frozen=True)
class Sweep:
    scenario: str = "paper-fig7"
    mission_s: float = 30.0
    n_faults: int = 4
    quiet_s: float = 20.0
    kinds: tuple[str, ...] = tuple(KINDS)

    def command(self, seed: int) -> str:
        kinds = "" if set(self.kinds) == set(KINDS) else f" --kinds {','.join(self.kinds)}"
        return (f"autopower sim {self.scenario} --seed {seed} --faults {self.n_faults} --mission {self.mission_s:g} "
                f"--quiet {self.quiet_s:g}{kinds}")


@dataclass(frozen=True)
class Verdict:
    seed: int
    ok: bool
    cpu_s: float
    trace_sha256: str
    first: str  # the first violation ("" when ok)


def run_seed(sweep: Sweep, seed: int) -> Verdict:
    from autopower.model.loading import load_scenario

    scenario = load_scenario(sweep.scenario)
    _, faults = draw(scenario, seed, sweep.n_faults, sweep.mission_s, sweep.kinds)
    started = time.process_time()
    before = logging.root.manager.disable
    logging.disable(logging.CRITICAL)  # the cores' logs: thousands of lines a seed, for no one
    try:
        result = run(SimConfig(scenario=scenario, seed=seed, faults=tuple(faults), mission_s=sweep.mission_s,
                               quiet_s=sweep.quiet_s))
    finally:
        logging.disable(before)
    first = f"{result.violations[0].invariant}: {result.violations[0].detail}" if result.violations else ""
    return Verdict(seed, result.ok, time.process_time() - started, result.trace_sha256, first)


def _one(args: tuple[Sweep, int]) -> Verdict:
    return run_seed(*args)


def sweep(plan: Sweep, seeds, jobs: int = 1) -> list[Verdict]:
    """Every seed's verdict, in the order of ``seeds`` (``jobs`` worker processes)."""
    work = [(plan, seed) for seed in seeds]
    if jobs <= 1:
        return [_one(w) for w in work]
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(_one, work, chunksize=max(1, len(work) // (8 * jobs))))
