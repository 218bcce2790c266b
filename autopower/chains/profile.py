"""Measure each component on this machine: the numbers of the paper's Fig. 5 for this platform."""

from __future__ import annotations

import statistics
import time
from typing import Any, Iterable

from autopower.chains.registry import component_types, make_component, make_source


def profile_components(runs: int = 50, *, robot: str = "r1", seed: int = 0,
                       types: Iterable[str] | None = None) -> dict[str, dict[str, Any]]:
    """Time ``run`` of every registered component type (or of ``types``) over ``runs`` steps.

    Each component processes its source's messages for seq 0..runs-1 in order (so the filter
    runs as it would on a robot); one extra warm-up step beforehand is not counted. Producing
    the inputs is not timed. Returns, per component type::

        {"runs": int, "latency_mean_s": float, "latency_median_s": float,
         "latency_min_s": float, "latency_max_s": float,
         "input_bytes": int, "input_bytes_max": int,     # mean (rounded) and largest message
         "output_bytes": int, "output_bytes_max": int}
    """
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise ValueError(f"runs must be a positive int, got {runs!r}")
    result: dict[str, dict[str, Any]] = {}
    for name in (component_types() if types is None else list(types)):
        source = make_source(name, robot, seed)
        component = make_component(name, robot, seed)
        warmup = make_component(name, robot, seed)
        warmup.run(source.produce(0))  # fills caches (maps, tables) before timing
        inputs = [source.produce(seq) for seq in range(runs)]
        latencies_s: list[float] = []
        output_sizes: list[int] = []
        for payload in inputs:
            start = time.perf_counter()
            output = component.run(payload)
            latencies_s.append(time.perf_counter() - start)
            output_sizes.append(len(output))
        input_sizes = [len(p) for p in inputs]
        result[name] = {
            "runs": runs,
            "latency_mean_s": statistics.fmean(latencies_s),
            "latency_median_s": statistics.median(latencies_s),
            "latency_min_s": min(latencies_s),
            "latency_max_s": max(latencies_s),
            "input_bytes": round(statistics.fmean(input_sizes)),
            "input_bytes_max": max(input_sizes),
            "output_bytes": round(statistics.fmean(output_sizes)),
            "output_bytes_max": max(output_sizes),
        }
    return result


def live_limit(scenario, profile: dict[str, dict[str, Any]], cores: int) -> tuple[float, float]:
    """(CPU seconds the mission's components need per virtual second, the speed-up that needs all
    ``cores``): each chain's runs per virtual second times its component's median run here. A
    team that ran live at that speed-up would spend all its CPU in the components, none in the
    runtime: no mission runs live faster on this machine."""
    need = sum(profile[stage.component]["latency_median_s"] / chain.period_s
               for chain in scenario.chains for stage in chain.stages)
    return need, cores / need if need > 0 else float("inf")


# How much slower than this machine each platform runs a component, unless told otherwise: this
# machine stands for the base station's laptop; the Sitsang (a 400 MHz XScale without an FPU) is
# x50, the geometric mean of the paper's two components (blob finder x11, localisation x243).
DEFAULT_PLATFORM_FACTORS = {"laptop": 1.0, "sitsang": 50.0}


def profile_plugin(component_cls: type, source_cls: type, runs: int = 50, *, robot: str = "r1",
                   seed: int = 0) -> dict[str, Any]:
    """Measure a plug-in component the way `profile_components` measures the built-in ones.

    Besides latency and message sizes: the size of its state (``export_state`` after the runs,
    largest seen after each run; 0 for a stateless component) and the time to export and import it.
    """
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise ValueError(f"runs must be a positive int, got {runs!r}")
    source = source_cls(robot, seed)
    inputs = [source.produce(seq) for seq in range(runs + 1)]
    component_cls(robot, seed).run(inputs[0])  # warm-up: caches, imports, tables
    component = component_cls(robot, seed)
    stateful = callable(getattr(component, "export_state", None))
    latencies_s: list[float] = []
    outputs: list[int] = []
    states: list[int] = []
    for payload in inputs[1:]:
        start = time.perf_counter()
        output = component.run(payload)
        latencies_s.append(time.perf_counter() - start)
        if not isinstance(output, bytes):
            raise TypeError(f"{component_cls.__qualname__}.run returned {type(output).__name__}, not bytes")
        outputs.append(len(output))
        if stateful:
            states.append(len(component.export_state()))
    export_s = import_s = 0.0
    if stateful:
        start = time.perf_counter()
        state = component.export_state()
        export_s = time.perf_counter() - start
        fresh = component_cls(robot, seed)
        start = time.perf_counter()
        fresh.import_state(state)
        import_s = time.perf_counter() - start
    input_sizes = [len(p) for p in inputs[1:]]
    return {
        "runs": runs,
        "latency_mean_s": statistics.fmean(latencies_s),
        "latency_median_s": statistics.median(latencies_s),
        "latency_max_s": max(latencies_s),
        "input_bytes_max": max(input_sizes),
        "output_bytes": round(statistics.fmean(outputs)),
        "output_bytes_max": max(outputs),
        "state_bytes": states[-1] if states else 0,
        "state_bytes_max": max(states, default=0),
        "export_s": export_s,
        "import_s": import_s,
    }


def components_block(name: str, component: str, source: str, measured: dict[str, Any],
                     factors: dict[str, float]) -> str:
    """The ``[components.NAME]`` table to paste into a scenario, with what to put in its chains."""
    median = measured["latency_median_s"]
    latencies = ", ".join(f"{platform} = {median * factor:.3g}" for platform, factor in factors.items())
    how = ", ".join(f"{p} x{f:g}" for p, f in factors.items())
    return "\n".join([
        f"[components.{name}]",
        f'implementation = "{component}"',
        f'source = "{source}"',
        f"latency_s = {{ {latencies} }}   # median {median * 1e3:.3g} ms here x platform factor ({how})",
        "",
        f"# in each [[chains]] that runs it: message_bytes = [{measured['input_bytes_max']}, "
        f"{measured['output_bytes_max']}]   (largest input, output seen)",
        f"# in [migration]: state_bytes = {{ {name} = {measured['state_bytes_max']} }}",
    ])
