"""`autopower analyze --pareto`: the lifetime/quality trade-offs of a scenario with quality variants."""

from __future__ import annotations

import json

import click
from rich.table import Table

from autopower.cli.options import console
from autopower.model.energy import round_lifetime
from autopower.model.scenario import Scenario


def print_front(s: Scenario, as_json: bool) -> None:
    """Every plan no other beats on both lifetime and mean chain quality, longest-lived first."""
    from autopower.model.variants import has_variants
    from autopower.planner import PlanRequest
    from autopower.planner.plan_choices import pareto_front
    from autopower.planner.problem import make_problem

    request = PlanRequest(scenario=s)
    front = pareto_front(make_problem(request), request)
    rows = [{"lifetime_s": round_lifetime(c.lifetime_s, s.lifetime_rounding_s), "lifetime_raw_s": c.lifetime_s,
             "quality": c.quality, "variants": c.variants, "levels": c.levels, "allocation": c.allocation,
             "media": c.network.media_by_group()} for c in front]
    if as_json:
        click.echo(json.dumps({"scenario": s.name, "accounting": s.accounting, "has_variants": has_variants(s),
                               "front": rows}, indent=2))
        return
    if not has_variants(s):
        console.print(f"{s.name} declares no quality variants: the front is its one optimum")
    table = Table("lifetime s", "quality", "variants", "levels", "allocation", "media",
                  title=f"{s.name} — {s.accounting} accounting — lifetime against quality")
    for r in rows:
        table.add_row(f"{r['lifetime_s']:.1f}", f"{r['quality']:.3f}",
                      ", ".join(f"{k}={v}" for k, v in r["variants"].items()) or "-",
                      ", ".join(f"{k}={v}" for k, v in r["levels"].items()) or "-",
                      ", ".join(f"{k}→{v}" for k, v in r["allocation"].items()),
                      ", ".join(f"{k}={v}" for k, v in r["media"].items()))
    console.print(table)
    if not rows:
        console.print("no plan fits the CPU and radio limits")
