"""The base station: the coordinator (plans, places, migrates), its process, the operator client."""

from autopower.basestation.coordinator import Coordinator, CoordinatorConfig
from autopower.basestation.operator import OperatorClient
from autopower.basestation.process import BaseStation, BaseStationConfig

__all__ = ["BaseStation", "BaseStationConfig", "Coordinator", "CoordinatorConfig", "OperatorClient"]
