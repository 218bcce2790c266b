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
