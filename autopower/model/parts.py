"""Names of the parts a node's metered energy is split into, shared by the meter and the recorder.

CPU: ``cpu_idle``, ``cpu_busy`` (component runs of the plan); radios: ``"<medium>:send"``,
``":receive"``, ``":sleep"``. The model's steady state covers exactly these. Overheads it does
not cover have parts of their own: ``"<medium>:migration"`` (a migrated stage's state on the
radios), ``"<medium>:recovery"`` (frames resent after a silent loss) and ``cpu_recovery`` (a
stage restarted without state recomputing inputs its lost predecessor may have run), ``cpu_backlog``
(the first run of an input that waited through a reconfiguration: produced before a stage's
instance started here without state, priced by the model where the stage was then), ``"<medium>:control"`` (the bytes
the node's links carried beyond the chain packets, measured: `autopower.node.control_meter`),
and ``cpu_runtime`` (the CPU the node's process spent beyond component code, on this machine, times
its platform's ``slowdown``: `BatteryMeter.charge_runtime`).
"""

from __future__ import annotations

CPU_IDLE, CPU_BUSY, CPU_RECOVERY, CPU_BACKLOG, CPU_RUNTIME = \
    "cpu_idle", "cpu_busy", "cpu_recovery", "cpu_backlog", "cpu_runtime"
OVERHEAD_KINDS = ("migration", "recovery", "backlog", "control", "runtime")
# what a run of a component is charged as: the plan's steady work, or an overhead of a reconfiguration
RUN_PARTS = {"chain": CPU_BUSY, "recovery": CPU_RECOVERY, "backlog": CPU_BACKLOG}


def radio_part(medium: str, what: str) -> str:
    """Name of a radio energy part: ``"<medium>:send"``, ``":receive"``, ``":sleep"``, ``":migration"``..."""
    return f"{medium}:{what}"


def overhead_kind(part_name: str) -> str | None:
    """``"migration"``, ``"recovery"``, ``"backlog"``, ``"control"`` or ``"runtime"`` for a part
    outside the model's steady state, else None."""
    if part_name == CPU_RECOVERY:
        return "recovery"
    if part_name == CPU_BACKLOG:
        return "backlog"
    if part_name == CPU_RUNTIME:
        return "runtime"
    kind = part_name.rpartition(":")[2]
    return kind if kind in OVERHEAD_KINDS else None
