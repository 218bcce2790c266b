"""AutoPower: energy-aware placement of robot software across a multi-robot team."""

from autopower.errors import (
    AutoPowerError,
    InfeasibleError,
    ProtocolError,
    RecordingError,
    ScenarioError,
)

__all__ = [
    "AutoPowerError",
    "InfeasibleError",
    "ProtocolError",
    "RecordingError",
    "ScenarioError",
]
