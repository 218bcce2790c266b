"""The node runtime: what every node of a team does with chain data, robots and the base station's
host alike — hosting stages, custody of frames until they are acknowledged, sequencing gates and
sink ledgers, holds for sinks out of reach, relaying, joins of DAG flows, and metering the battery.

`NodeRuntime` is the logic; the processes around it (`autopower.agent.process.Agent` on a robot,
`autopower.basestation.process.BaseStation` on the laptop) turn Zenoh, timers and files into its
calls.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.chains`,
`autopower.runtime`. Not the agent's process, nor the base station: both import this package.
"""

from autopower.node.meter import BatteryMeter
from autopower.node.runtime import NodeRuntime
from autopower.node.sequencing import SequenceGate, SinkLedger, fold_digest
from autopower.node.stages import Lifecycle

__all__ = ["BatteryMeter", "Lifecycle", "NodeRuntime", "SequenceGate", "SinkLedger", "fold_digest"]
