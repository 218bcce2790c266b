"""Offline analysis commands: `check`, `scenarios`, `analyze`, `plan`."""

from __future__ import annotations

import json

import click
from rich.table import Table

from autopower.cli.options import (
    ACCOUNTING_OPT,
    CONTROL_PLANE_OPT,
    ENERGY_OPT,
    JSON_OPT,
    POSITIVE,
    SCENARIO_ARG,
    build_scenario,
    console,
    profile_opts,
)
from autopower.cli.scenarios import scenarios
from autopower.model.scenario import Scenario


@click.command()
@SCENARIO_ARG
def check(scenario: str) -> None:
    """Validate a scenario file (and import its plug-in components) and summarise it."""
    s = build_scenario(scenario)
    console.print(f"[green]ok[/green] {s.source_path}: {s.name} — {len(s.robots)} robots, "
                  f"{len(s.chains)} chains, {len(s.stage_names())} stages, accounting {s.accounting}")


@click.command()
@SCENARIO_ARG
@ENERGY_OPT
@ACCOUNTING_OPT
@JSON_OPT
@click.option("--ties", default=4, show_default=True, help="How many tied optima to list per media pair.")
@click.option("--markdown", is_flag=True, help="Print a Markdown table (for reports).")
@profile_opts
@CONTROL_PLANE_OPT
@click.option("--only", type=click.Choice(["all", "paper", "optimal"]), default="all", show_default=True,
              help="Rows to show: everything, the paper's reference rows, or the optimum per media pair.")
@click.option("--pareto", is_flag=True,
              help="Print the Pareto front of lifetime against quality instead (scenarios with quality variants).")
def analyze(scenario: str, energy, accounting, as_json: bool, ties: int, markdown: bool, only: str,
            profile, as_platform, control_plane, pareto: bool) -> None:
    """Tabulate all-local, all-laptop and the optimum per topology and media pair (the paper's Fig 7)."""
    from autopower.planner.analysis import analyze as run

    s = build_scenario(scenario, energy, accounting=accounting, profile=profile, as_platform=as_platform,
                       control_plane=control_plane)
    if pareto:
        from autopower.cli.quality import print_front

        print_front(s, as_json)
        return
    rows, normaliser = run(s, max_ties=ties)
    if only == "paper":
        rows = [r for r in rows if r.label.startswith("paper-row-")]
    elif only == "optimal":
        rows = [r for r in rows if r.label in ("optimal", "infeasible")]  # one row per media pair
    if markdown:
        click.echo(markdown_table(s, rows, normaliser))
        return
    if as_json:
        click.echo(json.dumps({"scenario": s.name, "accounting": s.accounting,
                               "energies_j": s.energies_j(), "normalized_by_s": normaliser,
                               "rows": [r.to_dict(normaliser) for r in rows]}, indent=2))
        return
    stages = s.stage_names()
    table = Table(title=f"{s.name} — {s.accounting} accounting — energies "
                        + ", ".join(f"{r.name}={r.energy_j:g} J" for r in s.robots),
                  caption=f"normalized: divided by the shortest-lived feasible all-local row ({normaliser} s)")
    for col in ("topology", "laptop-robot", "robot-robot", "label", "lifetime s", "norm.", *stages, "bottleneck", "paper s"):
        table.add_column(col, justify="right" if col in ("lifetime s", "norm.", "paper s") else "left",
                         no_wrap=True)
    for row in rows:
        d = row.to_dict(normaliser)
        life = f"{d['lifetime_s']:.1f}" if d["lifetime_s"] else "infeasible"
        norm = f"{d['normalized']:.2f}" if d["normalized"] else ""
        paper = f"{row.paper_lifetime_s:.1f}" if row.paper_lifetime_s else ""
        style = "bold green" if d["label"] == "optimal" else None
        table.add_row(d["topology"], d["laptop_robot_medium"] or "-", d["robot_robot_medium"] or "-", d["label"],
                      life, norm, *[d["allocation"].get(st, "-") for st in stages], d["bottleneck"] or "-", paper,
                      style=style)
    console.print(table)
    for row in rows:
        if row.reason:
            console.print(f"{row.topology} {_media_text(row.media)}: infeasible: {row.reason}")


def _media_text(media: dict[str, str]) -> str:
    return ", ".join(f"{g}={m}" for g, m in media.items())


def markdown_table(s: Scenario, rows, normaliser) -> str:
    stages = s.stage_names()
    head = ["topology", "laptop–robot", "robot–robot", "row", "lifetime (s)", "norm.", *stages, "bottleneck"]
    if any(r.paper_lifetime_s for r in rows):
        head.append("paper (s)")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row in rows:
        d = row.to_dict(normaliser)
        cells = [d["topology"], d["laptop_robot_medium"] or "-", d["robot_robot_medium"] or "-", d["label"],
                 f"{d['lifetime_s']:.1f}" if d["lifetime_s"] else "infeasible",
                 f"{d['normalized']:.2f}" if d["normalized"] else "", *[d["allocation"].get(st, "-") for st in stages],
                 d["bottleneck"] or "-"]
        if "paper (s)" in head:
            cells.append(f"{row.paper_lifetime_s:.1f}" if row.paper_lifetime_s else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


@click.command("plan")
@SCENARIO_ARG
@ENERGY_OPT
@ACCOUNTING_OPT
@JSON_OPT
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None)
@click.option("--method", type=click.Choice(["auto", "exhaustive", "milp"]), default="auto", show_default=True)
@click.option("--disable", multiple=True, metavar="CHAIN", help="Plan without this chain (repeatable).")
@click.option("--without", multiple=True, metavar="ROBOT", help="Plan as if this robot were gone (repeatable).")
@click.option("--time-limit", type=POSITIVE, default=None, help="MILP time limit in seconds.")
@click.option("--no-bound", is_flag=True, help="Skip the time-sharing bound.")
@profile_opts
@CONTROL_PLANE_OPT
def plan_cmd(scenario, energy, accounting, as_json, topology, method, disable, without, time_limit, no_bound,
             profile, as_platform, control_plane) -> None:
    """The optimal allocation and media, with reasons and the time-sharing bound."""
    from autopower.planner import PlanRequest, plan

    s = build_scenario(scenario, energy, accounting=accounting, profile=profile, as_platform=as_platform,
                       control_plane=control_plane)
    for chain in disable:
        s.chain(chain)
    for robot in without:
        s.robot(robot)
    p = plan(PlanRequest(scenario=s, topology=topology, method=method, disabled_chains=frozenset(disable),
                         unavailable_nodes=frozenset(without), time_limit_s=time_limit, with_bound=not no_bound))
    if as_json:
        click.echo(json.dumps({"scenario": s.name, "accounting": s.accounting, **p.to_dict()}, indent=2))
        return
    ev = p.evaluation
    console.print(f"[bold]{s.name}[/bold] ({s.accounting} accounting, {p.network.topology}, media "
                  + ", ".join(f"{g}={m}" for g, m in p.network.media_by_group().items()) + ")")
    console.print(f"lifetime [bold green]{ev.lifetime_rounded_s:.1f} s[/bold green], bottleneck {ev.bottleneck}, "
                  f"method {p.method}{' (proven optimal)' if p.proven_optimal else f' (gap {p.mip_gap:.2%})'}")
    table = Table("stage", "host", "why")
    for stage, host in p.allocation.items():
        table.add_row(stage, host, p.reasons.get(stage, ""))
    for chain, why in p.dropped.items():
        table.add_row(chain, "-", why)
    console.print(table)
    for key, why in p.reasons.items():  # quality variants and DVFS levels (planner.plan_choices)
        if key.startswith(("variant:", "level:")):
            console.print(why)
    if p.quality is not None:
        console.print(f"mean quality {p.quality:.3f}")
    power = Table("robot", "energy J", "power W", "CPU W", "CPU util", "radios", "lifetime s")
    for name, rp in ev.robots.items():
        radios = ", ".join(f"{m} {r.total_w:.4f} W ({r.busy:.1%})" for m, r in rp.radios.items())
        power.add_row(name, f"{rp.energy_j:g}", f"{rp.total_w:.4f}", f"{rp.cpu_w:.4f}", f"{rp.cpu_utilisation:.1%}",
                      radios, f"{rp.lifetime_s:.1f}")
    console.print(power)
    if p.bound:
        b = p.bound
        console.print(f"time-sharing bound: {b.lifetime_s:.1f} s ({b.lifetime_s / ev.lifetime_s - 1:+.2%} over the "
                      f"best static plan{'' if b.proven else ', not proven tight'}) by switching between "
                      f"{len(b.schedule)} configuration(s)")
    if p.ties:
        console.print(f"{len(p.ties)} other configuration(s) tie with this one.")


COMMANDS = (check, scenarios, analyze, plan_cmd)
