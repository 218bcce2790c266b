"""Recording: every run into Rerun, and back out for replay and analysis.

Owns: the telemetry layout (entity paths, what each row means), the recorder each process wraps
its bus with (one file per process, one recording id, merged into `run.rrd`), drawing chain
outputs, and replay: the summary of a run, its exactly-once invariants and what-if replanning.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.chains`,
`autopower.planner`, `autopower.policies`, `autopower.simulation` (replay re-runs missions).
Not the processes: agents and the base station are handed a recording bus by their launcher.
"""
