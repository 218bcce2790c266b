"""Component types by the name scenario files use ("Blob", "Loc"), and factories for them.

To add a component type, write a source and a component following the protocols in
``autopower.chains.base`` and register them::

    register_component_type(ComponentType(
        name="Plan",
        make_source=lambda robot, seed: GoalSource(robot, seed),
        make_component=lambda robot, seed: Planner(robot, seed),
        score=score_plan,
        description="D* path planner on the building grid",
    ))
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from autopower.chains.base import Component, Source, UnknownComponentTypeError, check_seed, robot_key
from autopower.chains.blobfinder import BlobFinder, score_report
from autopower.chains.camera import CameraSource
from autopower.chains.mcl import MonteCarloLocaliser, score_estimate
from autopower.chains.teammap import JoinSource, TeamMap, score_map
from autopower.chains.variants import split_parameters, wrap_source
from autopower.chains.world import LocSource


@dataclass(frozen=True)
class ComponentType:
    """How to build one component type's source and component, and score its output."""

    name: str
    make_source: Callable[[str, int], Source]  # (robot, seed) -> the source on that robot
    make_component: Callable[[str, int], Component]  # (robot, seed) -> the component of that robot's chain
    score: Callable[[dict[str, Any], bytes], dict[str, float]]  # (ground truth, output) -> metrics
    description: str = ""


_REGISTRY: dict[str, ComponentType] = {}


def register_component_type(spec: ComponentType, *, replace: bool = False) -> None:
    """Make ``spec.name`` available to ``make_source``/``make_component``.

    Registering a name twice is an error unless ``replace=True`` (so two modules cannot
    silently fight over a name).
    """
    if not spec.name or not spec.name.isidentifier():
        raise ValueError(f"component type name must be an identifier like 'Blob', got {spec.name!r}")
    if spec.name in _REGISTRY and not replace:
        raise ValueError(f"component type {spec.name!r} is already registered (pass replace=True to override)")
    _REGISTRY[spec.name] = spec


def unregister_component_type(name: str) -> None:
    """Remove a registration (for tests and plug-ins that replace a built-in temporarily)."""
    get_component_type(name)  # raises the usual error if unknown
    del _REGISTRY[name]


def component_types() -> tuple[str, ...]:
    """Names of all registered component types, sorted."""
    return tuple(sorted(_REGISTRY))


def get_component_type(component_type: str) -> ComponentType:
    """The registration of ``component_type``; ``UnknownComponentTypeError`` (a KeyError) if none."""
    spec = _REGISTRY.get(component_type) if isinstance(component_type, str) else None
    if spec is None:
        known = ", ".join(repr(n) for n in component_types())
        hint = ""
        if isinstance(component_type, str) and "-" in component_type:
            base = component_type.split("-", 1)[0]
            if base in _REGISTRY:
                hint = f" ({component_type!r} looks like a component instance; its type is {base!r})"
        raise UnknownComponentTypeError(f"unknown component type {component_type!r}{hint}; known types: {known}")
    return spec


def make_source(component_type: str, robot: str, seed: int, parameters: dict | None = None) -> Source:
    """The source of ``robot``'s ``component_type`` chain; ``produce(seq)`` is deterministic in (robot, seed, seq).

    ``parameters``: a quality variant's (`autopower.chains.variants`: frame skipping)."""
    spec = get_component_type(component_type)
    robot_key(robot)  # validates the name
    source = spec.make_source(robot, check_seed(seed))
    return wrap_source(source, split_parameters(parameters)[0]) if parameters else source


def make_component(component_type: str, robot: str, seed: int, parameters: dict | None = None) -> Component:
    """The component of ``robot``'s ``component_type`` chain (e.g. "Loc" for robot "r2" = Loc-2).

    It processes that robot's data wherever it runs: ``make_component("Loc", "r2", s)`` on the
    laptop localises r2 in r2's building.
    """
    spec = get_component_type(component_type)
    robot_key(robot)
    params = split_parameters(parameters)[1]
    if not params:
        return spec.make_component(robot, check_seed(seed))
    try:  # a quality variant's constructor arguments (``n_particles``)
        return spec.make_component(robot, check_seed(seed), **params)
    except TypeError as exc:
        raise ValueError(f"component type {component_type!r} does not take variant parameters "
                         f"{', '.join(sorted(params))}: {exc}") from exc


def score_output(component_type: str, truth: dict[str, Any], output: bytes) -> dict[str, float]:
    """Accuracy metrics of a component's output against its source's ``ground_truth(seq)``."""
    return get_component_type(component_type).score(truth, output)


register_component_type(ComponentType(
    name="Blob",
    make_source=lambda robot, seed: CameraSource(robot, seed),
    make_component=lambda robot, seed: BlobFinder(robot),
    score=score_report,
    description="CMVision-style colour blob finder on 320x240 PPM camera frames",
))
register_component_type(ComponentType(
    name="Loc",
    make_source=lambda robot, seed: LocSource(robot, seed),
    make_component=lambda robot, seed, n_particles=1000: MonteCarloLocaliser(robot, seed, n_particles=n_particles),
    score=score_estimate,
    description="Monte-Carlo localisation from odometry and two laser scanners",
))
register_component_type(ComponentType(
    name="TeamMap",
    make_source=JoinSource,  # profiling only: the runtime feeds a fan-in stage from its inputs
    make_component=TeamMap,
    score=score_map,
    description="fan-in: merges every robot's localisation into the team's explored map (docs/concepts/chains.md)",
))
