"""The base station: the coordinator (plans, places, migrates), its process, the operator client.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.runtime`,
`autopower.planner`, `autopower.policies`. Not the agents: the two talk only through messages.
"""

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.basestation.operator import OperatorClient
from autopower.basestation.process import BaseStation, BaseStationConfig

__all__ = ["BaseStation", "BaseStationConfig", "Coordinator", "CoordinatorConfig", "OperatorClient"]
