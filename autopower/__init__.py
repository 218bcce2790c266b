"""AutoPower: energy-aware placement of robot software across a multi-robot team.

The public API for your own components (docs/tutorials/own-component.md): a component is a class
constructed as ``Cls(robot: str, seed: int)`` with ``run(self, payload: bytes) -> bytes`` (`Component`),
and, when it keeps state, ``export_state() -> bytes`` / ``import_state(bytes)``
(`StatefulComponent`); its chain's input comes from a source, ``Cls(robot, seed)`` with
``produce(self, seq: int) -> bytes`` (`Source`) and optionally ``ground_truth(seq)``
(`ScoredSource`). Name them in a scenario (``[components.X] implementation = "pkg.mod:Class"``,
``source = "pkg.mod:Class"``) or register them from a package's entry point
(group ``autopower.components``); `register_component_type` does it from code.

The component API is imported on first use: every AutoPower process and command imports this
package, and most of them (the CLI's operator commands, link proxies) never touch a component.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from autopower.errors import (
    AutoPowerError,
    InfeasibleError,
    ProtocolError,
    RecordingError,
    ScenarioError,
)

if TYPE_CHECKING:
    # For type checkers only (`X as X` marks a re-export); at run time __getattr__ imports on first use.
    from autopower.chains.base import (
        Component as Component,
        ComponentStateError as ComponentStateError,
        MalformedInputError as MalformedInputError,
        ScoredSource as ScoredSource,
        Source as Source,
        StatefulComponent as StatefulComponent,
    )
    from autopower.chains.plugins import (
        ENTRY_POINT_GROUP as ENTRY_POINT_GROUP,
        register_scenario_components as register_scenario_components,
    )
    from autopower.chains.registry import (
        ComponentType as ComponentType,
        make_component as make_component,
        make_source as make_source,
        register_component_type as register_component_type,
    )

_COMPONENT_API = {
    "Component": "autopower.chains.base",
    "ComponentStateError": "autopower.chains.base",
    "MalformedInputError": "autopower.chains.base",
    "ScoredSource": "autopower.chains.base",
    "Source": "autopower.chains.base",
    "StatefulComponent": "autopower.chains.base",
    "ENTRY_POINT_GROUP": "autopower.chains.plugins",
    "register_scenario_components": "autopower.chains.plugins",
    "ComponentType": "autopower.chains.registry",
    "make_component": "autopower.chains.registry",
    "make_source": "autopower.chains.registry",
    "register_component_type": "autopower.chains.registry",
}

__all__ = [
    "AutoPowerError",
    "InfeasibleError",
    "ProtocolError",
    "RecordingError",
    "ScenarioError",
    *sorted(_COMPONENT_API),
]


def __getattr__(name: str) -> Any:
    module = _COMPONENT_API.get(name)
    if module is None:
        raise AttributeError(f"module 'autopower' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_COMPONENT_API))
