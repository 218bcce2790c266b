"""Declared against measured quality of the real components' variants (`autopower quality`).

May import: `autopower.errors`, this package.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

from autopower.chains.registry import make_component, make_source, score_output
from autopower.chains.variants import measured_quality


def measure_variants(scenario, duration_s: float = 60.0) -> list[dict[str, Any]]:
    """Every variant of every component, run on the first chain that uses it for `duration_s`
    mission seconds of synthetic data: its declared score beside its measured quality (blob
    recall over every camera frame; localisation: 1 / (1 + mean position error in m), and the
    error itself). `scenario`: an `autopower.model.scenario.Scenario`."""
    rows = []
    for name, spec in scenario.components.items():
        chain = next((c for c in scenario.chains if c.stages[0].component == name), None)
        if not spec.variants or chain is None or name not in ("Blob", "Loc"):
            continue
        seed = zlib.crc32(f"{scenario.name}/{chain.name}".encode())  # the agents' chain seed
        for v in spec.variants:
            period = v.period_s or chain.period_s
            outputs = max(1, int(duration_s / period))
            source = make_source(name, chain.source, seed, dict(v.parameters) or None)
            component = make_component(name, chain.source, seed, dict(v.parameters) or None)
            found = total = err = 0.0
            for seq in range(outputs):
                q = measured_quality(name, source, seq, component.run(source.produce(seq)), score_output)
                if name == "Blob":
                    found, total = found + q["victims_found"], total + q["victims_total"]
                else:
                    err += q["position_error_m"]
            if name == "Blob":
                measured, metric = (found / total if total else math.nan), "recall over every camera frame"
            else:
                mean = err / outputs
                measured, metric = 1.0 / (1.0 + mean), f"1/(1+error); mean position error {mean:.3f} m"
            rows.append({"component": name, "variant": v.name, "chain": chain.name, "declared": v.quality,
                         "measured": measured, "metric": metric, "outputs": outputs,
                         "parameters": dict(v.parameters)})
    return rows
