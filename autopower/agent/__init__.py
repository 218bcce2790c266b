"""The robot agent: the process around a robot's node runtime (`autopower.node`).

`Agent` turns Zenoh, timers and files into the runtime's calls, publishes the robot's status,
keeps its resume file, detects silent peers and leads or joins subgroup rounds when the base
station is out of reach.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.chains`,
`autopower.runtime`, `autopower.planner`, `autopower.policies` (subgroup reallocation) and
`autopower.node`. Not the base station: the two talk only through messages.
"""

from autopower.agent.process import Agent, AgentConfig

__all__ = ["Agent", "AgentConfig"]
