"""Deterministic simulation of a whole team: the real cores of every robot and of the base station
(`NodeRuntime`, `Coordinator`) in one process, on one event queue, a simulated network and clock,
with faults drawn from a seed, an oracle that judges the run and a shrinker for failing schedules.

Owns: the event queue (`scheduler`), the network and its sessions (`network`), each process's bus
on it (`bus`), the shells that do what the processes do around the cores (`shells`), fault
schedules (`faults`) and carrying them out (`inject`), stand-in components (`components`), the
trace (`trace`), the oracle (`oracle`), one run (`team`), shrinking (`shrink`) and many seeds at
once (`sweep`).

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.chains`,
`autopower.runtime`, `autopower.policies`, `autopower.node`, `autopower.agent` (its resume file)
and `autopower.basestation`. Not `autopower.launch` or the CLI, which import this package.
"""

from autopower.teamsim.faults import KINDS, Fault, draw
from autopower.teamsim.oracle import Violation
from autopower.teamsim.team import SimConfig, SimResult, run

__all__ = ["KINDS", "Fault", "SimConfig", "SimResult", "Violation", "draw", "run"]
