"""Simulation: missions in virtual time, and scenario generators.

Owns: the discrete-event mission simulator (a whole mission under a policy and an event script, in
milliseconds of wall time) and the seeded random scenarios used by property tests and benchmarks.

May import: `autopower.errors`, `autopower.model`, `autopower.planner`, `autopower.policies`.
It writes recordings through a telemetry object it is handed, never by importing the recorder.
"""
