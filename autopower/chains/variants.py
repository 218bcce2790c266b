"""Quality variants of the real components, and their measured quality.

A scenario's variant hands its `parameters` here (see `autopower.model.variants`):
- ``every_nth_frame = n`` (any scored source, the blob finder's camera): frame skipping. The
  camera still captures at its own rate; the chain takes every n-th frame (step k of the chain is
  camera frame k·n), so its period is n times the camera's.
- any other parameter goes to the component's constructor (``n_particles`` for MCL).

Measured quality, against the synthetic world's ground truth:
- blob finder: recall = victims reported / victims in view, over *every* camera frame, each
  judged by the newest report the operator has (a skipped frame is judged by the report of the
  frame before it: what the operator sees then);
- localisation: position error (m) of each estimate against the true pose.

May import: `autopower.errors`, this package.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from autopower.chains.base import Source

SOURCE_PARAMETERS = ("every_nth_frame",)


class SkippingSource:
    """Every n-th step of a source: ``produce(k)`` is the inner source's step ``k·n``."""

    def __init__(self, inner: Source, every_nth: int):
        if isinstance(every_nth, bool) or not isinstance(every_nth, int) or not 1 <= every_nth <= 1000:
            raise ValueError(f"every_nth_frame must be an integer 1..1000, got {every_nth!r}")
        self.inner = inner
        self.every_nth = every_nth

    def produce(self, seq: int) -> bytes:
        return self.inner.produce(seq * self.every_nth)

    def ground_truth(self, seq: int) -> dict[str, Any]:
        return self.inner.ground_truth(seq * self.every_nth)

    def frames_of(self, seq: int) -> range:
        """The inner steps that step ``seq``'s output stands for, until the next one."""
        return range(seq * self.every_nth, (seq + 1) * self.every_nth)


def split_parameters(parameters: Mapping[str, Any] | None) -> tuple[dict[str, Any], dict[str, Any]]:
    """(source parameters, component parameters)."""
    parameters = dict(parameters or {})
    source = {k: parameters.pop(k) for k in SOURCE_PARAMETERS if k in parameters}
    return source, parameters


def wrap_source(source: Source, parameters: Mapping[str, Any]) -> Source:
    n = parameters.get("every_nth_frame", 1)
    return source if n == 1 and not isinstance(n, bool) else SkippingSource(source, n)


def measured_quality(component_type: str, source, seq: int, output: bytes, score_output) -> dict[str, float]:
    """What one output at the sink is worth against the ground truth (see the module docstring);
    ``score_output``: `autopower.chains.registry.score_output`."""
    inner = source.inner if isinstance(source, SkippingSource) else source
    frames = source.frames_of(seq) if isinstance(source, SkippingSource) else range(seq, seq + 1)
    if component_type == "Blob":
        total = found = 0.0
        for frame in frames:
            s = score_output("Blob", inner.ground_truth(frame), output)
            total += s["victims_total"]
            found += s["victims_found"]
        return {"victims_total": total, "victims_found": found,
                "recall": found / total if total else math.nan}
    if component_type == "Loc":
        return score_output("Loc", inner.ground_truth(frames[0]), output)
    return score_output(component_type, inner.ground_truth(frames[0]), output)

