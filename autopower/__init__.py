"""AutoPower: energy-aware placement of robot software across a multi-robot team.

The public API for your own components (see README "Your own components"): a component is a class
constructed as ``Cls(robot: str, seed: int)`` with ``run(self, payload: bytes) -> bytes`` (`Component`),
and, when it keeps state, ``export_state() -> bytes`` / ``import_state(bytes)``
(`StatefulComponent`); its chain's input comes from a source, ``Cls(robot, seed)`` with
``produce(self, seq: int) -> bytes`` (`Source`) and optionally ``ground_truth(seq)``
(`ScoredSource`). Name them in a scenario (``[components.X] implementation = "pkg.mod:Class"``,
``source = "pkg.mod:Class"``) or register them from a package's entry point
(group ``autopower.components``); `register_component_type` does it from code.
"""

from autopower.chains.base import (
    Component,
    ComponentStateError,
    MalformedInputError,
    ScoredSource,
    Source,
    StatefulComponent,
)
from autopower.chains.plugins import ENTRY_POINT_GROUP, register_scenario_components
from autopower.chains.registry import ComponentType, make_component, make_source, register_component_type
from autopower.errors import (
    AutoPowerError,
    InfeasibleError,
    ProtocolError,
    RecordingError,
    ScenarioError,
)

__all__ = [
    "ENTRY_POINT_GROUP",
    "AutoPowerError",
    "Component",
    "ComponentStateError",
    "ComponentType",
    "InfeasibleError",
    "MalformedInputError",
    "ProtocolError",
    "RecordingError",
    "ScenarioError",
    "ScoredSource",
    "Source",
    "StatefulComponent",
    "make_component",
    "make_source",
    "register_component_type",
    "register_scenario_components",
]
