"""Components of your own: classes named in a scenario, or registered by an installed package.

A scenario names a plug-in by import path::

    [components.Motion]
    implementation = "motion_demo.motion:MotionDetector"   # the component class
    source = "motion_demo.camera:GreyCamera"               # the chain's input, on its source robot
    latency_s = { sitsang = 0.05, laptop = 0.004 }

or only by name (``[components.Motion] latency_s = ...``) when an installed package declares it
in the entry-point group ``autopower.components``::

    [project.entry-points."autopower.components"]
    Motion = "motion_demo.motion:MotionDetector"    # a component class with a SOURCE attribute

`register_scenario_components` imports and checks every one of them and registers it under its
scenario name, so `make_component`/`make_source` build it on any node. Every failure is one
`ScenarioError` line naming the scenario file and line and what went wrong: module not found,
attribute missing, not a component (no ``run``), not a source (no ``produce``), a constructor
that cannot be called as ``Cls(robot, seed)``. Nothing is constructed here: a constructor may be
expensive, and it runs on the node that hosts the component.

It is called before anything starts: by the CLI when it loads a scenario (every command), and
by each agent and base-station process again for itself. The scenario model stays pure data.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Mapping

from autopower.chains.registry import ComponentType, component_types, get_component_type, register_component_type
from autopower.errors import ScenarioError

ENTRY_POINT_GROUP = "autopower.components"


def register_scenario_components(components: Mapping[str, Any], *, require_code: bool = False) -> list[str]:
    """Import, check and register every plug-in among a scenario's ``components``.

    ``components`` maps names to `autopower.model.scenario.ComponentSpec`-like objects
    (``name``, ``implementation``, ``source``, ``defined_at``). A name that is already registered
    (a built-in, or the same plug-in registered before) is left as it is unless the scenario
    names a different implementation for it, which is an error. A name with no code anywhere is
    fine for planning (synthetic scenarios), an error with ``require_code`` (a team to run).
    Returns the names registered now.
    """
    registered = []
    for name, spec in components.items():
        where = dict(getattr(spec, "defined_at", {}) or {})
        table = where.get("latency_s", "scenario")  # the [components.NAME] table's line
        implementation = getattr(spec, "implementation", None)
        if implementation is None:
            if name in component_types():
                continue
            found = _from_entry_point(name, table)
            if found is None:
                if require_code:
                    raise ScenarioError(
                        f"{table}: components.{name}: no code for this component: not built in "
                        f"({', '.join(component_types())}), no implementation = \"pkg.mod:Class\" line, and no "
                        f"installed package declares it in {ENTRY_POINT_GROUP}")
                continue  # planning-only component types (synthetic scenarios) need no code
            component_cls, source_cls, origin = found
            what_component = what_source = f"{table}: components.{name} (entry point {origin!r})"
        else:
            what_component = f"{where.get('implementation', table)}: components.{name}.implementation"
            what_source = f"{where.get('source', table)}: components.{name}.source"
            component_cls = load_class(implementation, what_component)
            source_cls = load_class(spec.source, what_source)
            origin = implementation
        check_component_class(component_cls, what_component)
        check_source_class(source_cls, what_source)
        existing = get_component_type(name) if name in component_types() else None
        if existing is not None:
            if getattr(existing, "origin", None) == (component_cls, source_cls):
                continue
            raise ScenarioError(f"{where.get('implementation', table)}: components.{name}: the name {name!r} is "
                                f"already a component type ({existing.description or 'built in'}); give yours "
                                f"another name")
        register_component_type(plugin_type(name, component_cls, source_cls, origin))
        registered.append(name)
    return registered


def plugin_type(name: str, component_cls: type, source_cls: type, origin: str) -> ComponentType:
    """The registration of a plug-in: built as ``Cls(robot, seed)``; scored by nothing."""
    return PluginType(
        name=name,
        make_source=lambda robot, seed: source_cls(robot, seed),
        make_component=lambda robot, seed: component_cls(robot, seed),
        score=_no_score,
        description=f"plug-in {origin}",
        origin=(component_cls, source_cls),
    )


@dataclass(frozen=True)
class PluginType(ComponentType):
    """A `ComponentType` that remembers the classes it came from (to tell a re-registration)."""

    origin: tuple[type, type] | None = None


def _no_score(truth: dict[str, Any], output: bytes) -> dict[str, float]:
    return {}


def load_class(path: str, what: str) -> type:
    """Import ``"package.module:Class"``; one `ScenarioError` line saying what failed."""
    module_name, _, attr = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        missing = exc.name or module_name
        raise ScenarioError(f"{what} = {path!r}: module {missing!r} not found; install the package that provides "
                            f"it (pip install ...) or put it on PYTHONPATH") from None
    except Exception as exc:  # the user's module itself failed to import
        raise ScenarioError(f"{what} = {path!r}: importing {module_name!r} failed: "
                            f"{type(exc).__name__}: {_one_line(exc)}") from None
    obj: Any = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ScenarioError(f"{what} = {path!r}: module {module_name!r} has no attribute {attr!r}; "
                                f"check the class name")
        obj = getattr(obj, part)
    if not inspect.isclass(obj):
        raise ScenarioError(f"{what} = {path!r}: {attr!r} is a {type(obj).__name__}, not a class")
    return obj


def check_component_class(cls: type, what: str) -> None:
    """A component class: ``Cls(robot, seed)``, a ``run`` method, and both state methods or neither."""
    name = cls.__qualname__
    if not callable(getattr(cls, "run", None)):
        raise ScenarioError(f"{what}: {name} is not a component: it has no run(self, payload: bytes) -> bytes "
                            f"method (see autopower.Component)")
    state = [m for m in ("export_state", "import_state") if callable(getattr(cls, m, None))]
    if len(state) == 1:
        lacking = ({"export_state", "import_state"} - set(state)).pop()
        raise ScenarioError(f"{what}: {name} has {state[0]} but no {lacking}; a component that migrates with "
                            f"its state needs both (see autopower.StatefulComponent)")
    _check_constructor(cls, what)


def check_source_class(cls: type, what: str) -> None:
    """A source class: ``Cls(robot, seed)`` and a ``produce`` method."""
    if not callable(getattr(cls, "produce", None)):
        raise ScenarioError(f"{what}: {cls.__qualname__} is not a source: it has no produce(self, seq: int) -> "
                            f"bytes method (see autopower.Source)")
    _check_constructor(cls, what)


def _check_constructor(cls: type, what: str) -> None:
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):
        return  # a class implemented in C: nothing to check before calling it
    try:
        signature.bind("r1", 0)
    except TypeError as exc:
        raise ScenarioError(f"{what}: {cls.__qualname__}{signature} cannot be constructed as "
                            f"{cls.__qualname__}(robot, seed) ({exc})") from None


def _from_entry_point(name: str, where: str) -> tuple[type, type, str] | None:
    """(component class, source class, origin) of an installed package's entry point ``name``."""
    matches = [ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not matches:
        return None
    if len({ep.value for ep in matches}) > 1:
        raise ScenarioError(f"{where}: components.{name}: several installed packages declare it in "
                            f"{ENTRY_POINT_GROUP}: {', '.join(sorted(ep.value for ep in matches))}")
    ep = matches[0]
    what = f"{where}: components.{name} (entry point {ENTRY_POINT_GROUP} {name} = {ep.value!r})"
    component_cls = load_class(ep.value, what)
    source = getattr(component_cls, "SOURCE", None)
    if source is None:
        raise ScenarioError(f"{what}: {component_cls.__qualname__} has no SOURCE attribute naming its source "
                            f"class; add SOURCE = YourSource (or \"pkg.mod:Class\"), or name both in the scenario")
    source_cls = load_class(source, f"{what}.SOURCE") if isinstance(source, str) else source
    if not inspect.isclass(source_cls):
        raise ScenarioError(f"{what}: SOURCE is a {type(source_cls).__name__}, not a class")
    return component_cls, source_cls, ep.value


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else ""
