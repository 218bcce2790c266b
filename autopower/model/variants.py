"""Quality as a variable: components with variants (the paper's future work).

A component may declare variants, e.g. the blob-finder at 4, 2 or 1 frames per second, or MCL
with 1000, 300 or 100 particles. Each variant has a quality score in (0, 1] and may override the
chain's period, the component's latency per platform, and the sizes of the stage's input and
output messages; `parameters` are handed to the real component (frame skipping, particle count).

Rules:
- A chain runs one variant of its (at most one) stage whose component declares variants; a chain
  without such a stage has quality 1 and is the one-variant special case.
- A chain's `min_quality` excludes variants scoring below it.
- A plan's quality is the mean quality of the chains it places.
- `quality_weight` w (scenario `[mission]`) picks a point on the Pareto front of lifetime against
  quality: the one maximising (1 - w) * L / L_best + w * Q. w = 0 (the default) maximises lifetime
  (ties broken by quality); the planner then runs every chain at its cheapest admissible variant.
- When no variant is chosen for a chain (evaluating a given allocation), its first declared
  variant runs: declare the full-quality one first.

For the model, a chosen variant is a derived component type "<component>@<variant>" with the
variant's latencies, and a derived chain with its period and message sizes (`apply_variants`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping

from autopower.errors import ScenarioError
from autopower.model.scenario import Chain, ComponentSpec, Scenario


@dataclass(frozen=True, kw_only=True)
class Variant:
    name: str
    quality: float  # (0, 1]: declared; the recording measures the real one
    period_s: float | None = None  # None: the chain's period
    latency_s: Mapping[str, float] | None = None  # None: the component's
    message_bytes: tuple[int, int] | None = None  # (input, output) of the stage; None: the chain's
    parameters: Mapping[str, Any] = field(default_factory=dict)  # for the real component


def variant_stage(scenario: Scenario, chain: Chain) -> int | None:
    """Index of the chain's stage whose component declares variants, or None."""
    for k, stage in enumerate(chain.stages):
        if scenario.components[stage.component].variants:
            return k
    return None


def variants_of(scenario: Scenario, chain: Chain) -> tuple[Variant, ...]:
    k = variant_stage(scenario, chain)
    return () if k is None else scenario.components[chain.stages[k].component].variants


def has_variants(scenario: Scenario) -> bool:
    return any(spec.variants for spec in scenario.components.values())


def admissible(scenario: Scenario, chain: Chain) -> tuple[Variant, ...]:
    """The chain's variants meeting its min_quality, best quality first (() = no variants)."""
    return tuple(v for v in variants_of(scenario, chain) if v.quality >= chain.min_quality - 1e-12)


def derived_component(component: str, variant: str) -> str:
    return f"{component}@{variant}"


def variant_chain(scenario: Scenario, chain: Chain, variant: Variant, *, rename: bool = False) -> Chain:
    """The chain running `variant`. rename: distinct chain and stage names "<name>@<variant>"
    (for planners that hold every variant of a chain side by side)."""
    k = variant_stage(scenario, chain)
    stage = chain.stages[k]
    stages = list(chain.stages)
    stages[k] = dataclasses.replace(stage, component=derived_component(stage.component, variant.name),
                                    name=f"{stage.name}@{variant.name}" if rename else stage.name)
    sizes = list(chain.message_bytes)
    if variant.message_bytes is not None:
        sizes[k], sizes[k + 1] = variant.message_bytes
    return dataclasses.replace(chain, name=f"{chain.name}@{variant.name}" if rename else chain.name,
                               period_s=variant.period_s or chain.period_s, stages=tuple(stages),
                               message_bytes=tuple(sizes))


def with_variant_components(scenario: Scenario) -> Scenario:
    """The scenario with a derived component type for every variant (the chains unchanged)."""
    components = dict(scenario.components)
    for name, spec in scenario.components.items():
        for v in spec.variants:
            components[derived_component(name, v.name)] = dataclasses.replace(
                spec, name=derived_component(name, v.name), latency_s={**spec.latency_s, **(v.latency_s or {})},
                variants=())
    return dataclasses.replace(scenario, components=components)


def default_choice(scenario: Scenario) -> dict[str, str]:
    return {c.name: variants_of(scenario, c)[0].name for c in scenario.chains if variants_of(scenario, c)}


def check_choice(scenario: Scenario, choice: Mapping[str, str]) -> None:
    for chain_name, variant in choice.items():
        chain = scenario.chain(chain_name)
        names = [v.name for v in variants_of(scenario, chain)]
        if variant not in names:
            raise ScenarioError(f"variant {variant!r} for chain {chain_name}: "
                                + (f"its variants are {', '.join(names)}" if names else "it has no variants"))


def apply_variants(scenario: Scenario, choice: Mapping[str, str] | None = None) -> Scenario:
    """The scenario with each chain running its chosen variant (unchosen: the first declared)."""
    if not has_variants(scenario):
        return scenario
    choice = {**default_choice(scenario), **(choice or {})}
    check_choice(scenario, choice)
    chains = []
    for chain in scenario.chains:
        if chain.name in choice:
            variant = next(v for v in variants_of(scenario, chain) if v.name == choice[chain.name])
            chain = variant_chain(scenario, chain, variant)
        chains.append(chain)
    return dataclasses.replace(with_variant_components(scenario), chains=tuple(chains))


def chain_quality(scenario: Scenario, chain: Chain, variant: str | None) -> float:
    if variant is None:
        return 1.0
    return next(v.quality for v in variants_of(scenario, chain) if v.name == variant)


def plan_quality(scenario: Scenario, chains, choice: Mapping[str, str]) -> float:
    """Mean quality of the placed chains (1.0 for chains without variants)."""
    chains = list(chains)
    if not chains:
        return 1.0
    return sum(chain_quality(scenario, c, choice.get(c.name)) for c in chains) / len(chains)


# ---- loading (called by autopower.model.loading) --------------------------------------------------
def parse_variants(parser, obj: Any, path: str, platforms: Mapping[str, Any]) -> tuple[Variant, ...]:
    """`[components.NAME.variants.VARIANT]` tables, in file order; errors name file:line:field."""
    obj = parser.table(obj, path, obj.keys() if isinstance(obj, dict) else [])
    out = []
    for name, spec in obj.items():
        vpath = f"{path}.{name}"
        spec = parser.section(spec, vpath, "components.<component>.variants.<variant>")
        quality = parser.number(spec, "quality", vpath, positive=True)
        if quality > 1:
            raise parser.fail(f"{vpath}.quality", f"found {quality}", "a score in (0, 1]")
        latency = None
        if "latency_s" in spec:
            lat = parser.table(spec["latency_s"], f"{vpath}.latency_s", platforms)
            latency = {p: parser.number(lat, p, f"{vpath}.latency_s", positive=True) for p in lat}
        sizes = spec.get("message_bytes")
        if sizes is not None and (not isinstance(sizes, list) or len(sizes) != 2 or not all(
                isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= 2**30 for n in sizes)):
            raise parser.fail(f"{vpath}.message_bytes", f"found {sizes!r}",
                              "[input, output]: two non-negative integers (the stage's input and output message)")
        params = spec.get("parameters", {})
        if not isinstance(params, dict) or not all(
                isinstance(v, (int, float, str)) and not isinstance(v, bool) for v in params.values()):
            raise parser.fail(f"{vpath}.parameters", f"found {params!r}", "a table of numbers or strings")
        out.append(Variant(name=name, quality=quality,
                           period_s=parser.number(spec, "period_s", vpath, positive=True) if "period_s" in spec else None,
                           latency_s=latency, message_bytes=tuple(sizes) if sizes is not None else None,
                           parameters=dict(params)))
    if len({v.name for v in out}) != len(out) or any("@" in v.name for v in out):
        raise parser.fail(path, "a variant name contains '@'", "names without '@'")
    return tuple(out)


def check_chain_variants(parser, chains, components: Mapping[str, ComponentSpec]) -> None:
    """At most one variant stage per chain; a min_quality some variant meets."""
    for i, chain in enumerate(chains):
        with_variants = [s for s in chain.stages if components[s.component].variants]
        if len(with_variants) > 1:
            raise parser.fail(f"chains[{i}]", f"stages {', '.join(s.name for s in with_variants)} all have "
                              "components with variants", "at most one stage per chain whose component has variants")
        best = max(v.quality for v in components[with_variants[0].component].variants) if with_variants else 1.0
        if chain.min_quality > best:
            what = f"the best variant of {with_variants[0].component} scores {best}" if with_variants \
                else "a chain without variants has quality 1"
            raise parser.fail(f"chains[{i}].min_quality", f"found {chain.min_quality} but {what}",
                              f"a floor of at most {best}")


def runtime_component(scenario: Scenario, component: str) -> tuple[str, dict[str, Any]]:
    """(component type to build, the variant's parameters) for a stage's component name, which
    `apply_variants` makes "<type>@<variant>"; ({}: the type as declared)."""
    base, _, variant = component.partition("@")
    if not variant or base not in scenario.components:
        return component, {}
    spec = next((v for v in scenario.components[base].variants if v.name == variant), None)
    return base, dict(spec.parameters) if spec else {}
