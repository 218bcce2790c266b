"""The base station: the coordinator (plans, places, migrates), its process, the operator client.

May import: `autopower.errors`, `autopower.model`, `autopower.protocol`, `autopower.runtime`,
`autopower.planner`, `autopower.policies`. Not the agents: the two talk only through messages.
"""

import importlib

# Imported when first named (PEP 562): the operator's client (`autopower status`) needs none of the
# coordinator's planner, numpy or networkx (0.9 s a command).
_EXPORTS = {"BaseStation": "process", "BaseStationConfig": "process", "Coordinator": "coordinator",
            "CoordinatorConfig": "coordinator", "OperatorClient": "operator"}

__all__ = ["BaseStation", "BaseStationConfig", "Coordinator", "CoordinatorConfig", "OperatorClient"]


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
