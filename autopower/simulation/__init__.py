"""Simulation: missions in virtual time, and scenario generators.

Owns: the discrete-event mission simulator (a whole mission under a policy and an event script, in
milliseconds of wall time), the seeded random scenarios used by property tests and benchmarks,
and the paper's mission on N robots as a scenario file (`autopower scenarios fleet`).

May import: `autopower.errors`, `autopower.model`, `autopower.planner`, `autopower.policies`.
It writes recordings through a telemetry object it is handed, never by importing the recorder.
"""
