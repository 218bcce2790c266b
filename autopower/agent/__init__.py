"""The robot agent: hosts components, meters the battery, forwards, publishes status.

`NodeRuntime` (what every node does with chain data, also used by the base station for the
laptop) is the logic; `Agent` is the process around it.
"""

from autopower.agent.meter import BatteryMeter
from autopower.agent.node import Lifecycle, NodeRuntime
from autopower.agent.process import Agent, AgentConfig
from autopower.agent.sequencing import SequenceGate, SinkLedger, fold_digest

__all__ = ["Agent", "AgentConfig", "BatteryMeter", "Lifecycle", "NodeRuntime", "SequenceGate", "SinkLedger",
           "fold_digest"]
