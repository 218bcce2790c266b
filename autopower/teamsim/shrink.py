"""Shrinking a failing fault schedule to the smallest one that still fails the same way.

Delta debugging (Zeller's ddmin) drops faults: chunks of the schedule first, then single faults,
keeping any smaller schedule that still violates the same invariant. Then each remaining fault
is shortened (its duration halved while it still fails). Every try is a whole run of the same
seed, so the result replays as it is.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from autopower.teamsim.faults import Fault
from autopower.teamsim.team import SimConfig, SimResult, run

MIN_DURATION_S = 0.05


def fails_like(result: SimResult, invariant: str) -> bool:
    return any(v.invariant == invariant for v in result.violations)


def shrink(config: SimConfig, invariant: str, *, on_try: Callable[[int, list[Fault], bool], None] | None = None,
           max_runs: int = 200) -> tuple[list[Fault], SimResult | None]:
    """The smallest schedule found that still violates ``invariant`` and the run that shows it
    (None if even the given schedule passes)."""
    tries = 0
    last: SimResult | None = None

    def failing(faults: list[Fault]) -> bool:
        nonlocal tries, last
        tries += 1
        result = run(dataclasses.replace(config, faults=tuple(faults)))
        bad = fails_like(result, invariant)
        if bad:
            last = result
        if on_try is not None:
            on_try(tries, faults, bad)
        return bad

    faults = list(config.faults)
    if not failing(faults):
        return faults, None
    n = 2
    while len(faults) >= 2 and tries < max_runs:
        size = len(faults) // n or 1
        chunks = [faults[i:i + size] for i in range(0, len(faults), size)]
        for chunk in chunks:
            rest = [f for f in faults if f not in chunk]
            if rest != faults and failing(rest):
                faults, n = rest, max(n - 1, 2)
                break
        else:
            if n >= len(faults):
                break
            n = min(2 * n, len(faults))
    if len(faults) == 1 and tries < max_runs and failing([]):
        faults = []
    for i in range(len(faults)):
        while faults[i].duration > 2 * MIN_DURATION_S and tries < max_runs:
            shorter = dataclasses.replace(faults[i], duration=round(faults[i].duration / 2, 3))
            trial = faults[:i] + [shorter] + faults[i + 1:]
            if not failing(trial):
                break
            faults = trial
    return faults, last
