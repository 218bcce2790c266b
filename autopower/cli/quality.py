"""Quality variants: `autopower analyze --pareto` (lifetime against quality) and `autopower quality`
(declared scores against what the real components measure on the synthetic world)."""

from __future__ import annotations

import json

import click
from rich.table import Table

from autopower.cli.options import JSON_OPT, POSITIVE, SCENARIO_ARG, build_scenario, console
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


@click.command("quality")
@SCENARIO_ARG
@JSON_OPT
@click.option("--duration", type=POSITIVE, default=60.0, show_default=True,
              help="Mission seconds of synthetic sensor data to run each variant on.")
def quality_cmd(scenario: str, as_json: bool, duration: float) -> None:
    """Run every quality variant's real component on the synthetic world; declared vs measured quality."""
    from autopower.chains.quality import measure_variants

    s = build_scenario(scenario)
    rows = measure_variants(s, duration)
    if as_json:
        click.echo(json.dumps({"scenario": s.name, "duration_s": duration, "variants": rows}, indent=2))
        return
    if not rows:
        console.print(f"{s.name} declares no quality variants")
        return
    table = Table("component", "variant", "chain", "declared", "measured", "metric", "outputs",
                  title=f"{s.name} — declared against measured quality ({duration:g} s of data)")
    for r in rows:
        table.add_row(r["component"], r["variant"], r["chain"], f"{r['declared']:.2f}",
                      f"{r['measured']:.3f}", r["metric"], str(r["outputs"]))
    console.print(table)


COMMANDS = (quality_cmd,)
