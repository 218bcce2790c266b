"""The robot agent: hosts components, meters the battery, forwards, publishes status.

`NodeRuntime` (what every node does with chain data, also used by the base station for the
laptop) is the logic; `Agent` is the process around it.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.chains`,
`autopower.runtime`, `autopower.planner` and `autopower.policies` (subgroup reallocation). Not the
base station: the two talk only through messages.
"""

from autopower.agent.meter import BatteryMeter
from autopower.agent.node import NodeRuntime
from autopower.agent.process import Agent, AgentConfig
from autopower.agent.sequencing import SequenceGate, SinkLedger, fold_digest
from autopower.agent.stages import Lifecycle

__all__ = ["Agent", "AgentConfig", "BatteryMeter", "Lifecycle", "NodeRuntime", "SequenceGate", "SinkLedger",
           "fold_digest"]
