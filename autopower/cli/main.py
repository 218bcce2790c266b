"""The `autopower` command line.

Every AutoPowerError becomes one line on stderr and exit status 2: what was wrong, where, and
what to do. Tracebacks are for bugs only.
"""

from __future__ import annotations

import json
import sys

import click
from rich.console import Console
from rich.table import Table

from autopower.cli.entry import run_command
from autopower.errors import AutoPowerError
from autopower.model.scenario import Scenario, builtin_scenarios, load_scenario

# Piped output (CI logs, `| less`) would otherwise be cut to 80 columns and truncate the tables.
console = Console() if sys.stdout.isatty() else Console(width=200)


def parse_energies(values: tuple[str, ...]) -> dict[str, float]:
    out = {}
    for item in values:
        name, sep, joules = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(joules)
        except ValueError:
            raise AutoPowerError(f"--energy {item!r}: expected ROBOT=JOULES, e.g. --energy r1=32000") from None
    return out


def scenario_from(name: str, energy: tuple[str, ...] = (), accounting: str | None = None,
                  profile: str | None = None, as_platform: str | None = None) -> Scenario:
    scenario = load_scenario(name)
    if profile:
        scenario = scenario.with_latency_profile(profile, as_platform or scenario.basestation_platform)
    if energy:
        scenario = scenario.with_energies(parse_energies(energy))
    return scenario.with_accounting(accounting)


SCENARIO_ARG = click.argument("scenario", default="paper-fig7", metavar="SCENARIO")
ENERGY_OPT = click.option("--energy", multiple=True, metavar="ROBOT=J", help="Override a robot's starting energy (repeatable).")
ACCOUNTING_OPT = click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None,
                              help="Message accounting (default: the scenario's).")
def profile_opts(f):
    f = click.option("--latency-profile", "profile", default=None, metavar="FILE",
                     help="Latencies measured by `autopower profile` ...")(f)
    return click.option("--as-platform", default=None, metavar="PLATFORM",
                        help="... applied to this platform (default: the base station's).")(f)


JSON_OPT = click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """AutoPower: energy-aware placement of robot software across a multi-robot team.

    SCENARIO is a built-in name (paper-fig7, paper-fig8, ...) or a path to a .toml file.
    """


@cli.command()
@SCENARIO_ARG
def check(scenario: str) -> None:
    """Validate a scenario file and summarise it."""
    s = load_scenario(scenario)
    console.print(f"[green]ok[/green] {s.source_path}: {s.name} — {len(s.robots)} robots, "
                  f"{len(s.chains)} chains, {len(s.stage_names())} stages, accounting {s.accounting}")


@cli.command("scenarios")
def list_scenarios() -> None:
    """List the built-in scenarios."""
    for name in builtin_scenarios():
        console.print(f"{name}: {load_scenario(name).description}")


@cli.command()
@SCENARIO_ARG
@ENERGY_OPT
@ACCOUNTING_OPT
@JSON_OPT
@click.option("--ties", default=4, show_default=True, help="How many tied optima to list per media pair.")
@click.option("--markdown", is_flag=True, help="Print a Markdown table (for reports).")
@profile_opts
@click.option("--only", type=click.Choice(["all", "paper", "optimal"]), default="all", show_default=True,
              help="Rows to show: everything, the paper's reference rows, or the optimum per media pair.")
def analyze(scenario: str, energy, accounting, as_json: bool, ties: int, markdown: bool, only: str,
            profile, as_platform) -> None:
    """Tabulate all-local, all-laptop and the optimum per topology and media pair (the paper's Fig 7)."""
    from autopower.planner.analysis import analyze as run

    s = scenario_from(scenario, energy, accounting, profile, as_platform)
    rows, normaliser = run(s, max_ties=ties)
    if only == "paper":
        rows = [r for r in rows if r.label.startswith("paper-row-")]
    elif only == "optimal":
        rows = [r for r in rows if r.label == "optimal"]
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
                      life, norm, *[d["allocation"][st] for st in stages], d["bottleneck"] or "-", paper, style=style)
    console.print(table)


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
                 f"{d['normalized']:.2f}" if d["normalized"] else "", *[d["allocation"][st] for st in stages],
                 d["bottleneck"] or "-"]
        if "paper (s)" in head:
            cells.append(f"{row.paper_lifetime_s:.1f}" if row.paper_lifetime_s else "")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


@cli.command("plan")
@SCENARIO_ARG
@ENERGY_OPT
@ACCOUNTING_OPT
@JSON_OPT
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None)
@click.option("--method", type=click.Choice(["auto", "exhaustive", "milp"]), default="auto", show_default=True)
@click.option("--disable", multiple=True, metavar="CHAIN", help="Plan without this chain (repeatable).")
@click.option("--without", multiple=True, metavar="ROBOT", help="Plan as if this robot were gone (repeatable).")
@click.option("--time-limit", type=float, default=None, help="MILP time limit in seconds.")
@click.option("--no-bound", is_flag=True, help="Skip the time-sharing bound.")
@profile_opts
def plan_cmd(scenario, energy, accounting, as_json, topology, method, disable, without, time_limit, no_bound,
             profile, as_platform) -> None:
    """The optimal allocation and media, with reasons and the time-sharing bound."""
    from autopower.planner import PlanRequest, plan

    s = scenario_from(scenario, energy, accounting, profile, as_platform)
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


@cli.command()
@click.option("--runs", default=50, show_default=True, help="Runs per component.")
@click.option("--out", default=None, metavar="FILE", help="Write the profile (TOML) here.")
@JSON_OPT
def profile(runs: int, out: str | None, as_json: bool) -> None:
    """Measure each real component's latency and message sizes on this machine.

    The file it writes plugs into any scenario: `autopower plan --latency-profile FILE
    --as-platform laptop` plans as if the base station were this machine.
    """
    import platform as host
    from datetime import datetime, timezone

    from autopower.chains.profile import profile_components

    if runs < 1:
        raise AutoPowerError(f"--runs must be >= 1, got {runs}")
    result = profile_components(runs)
    if as_json:
        click.echo(json.dumps(result, indent=2))
    else:
        table = Table("component", "mean ms", "median ms", "max ms", "input B", "output B", title=f"{runs} runs on this machine")
        for name, r in result.items():
            table.add_row(name, f"{r['latency_mean_s'] * 1e3:.3f}", f"{r['latency_median_s'] * 1e3:.3f}",
                          f"{r['latency_max_s'] * 1e3:.3f}", str(r["input_bytes"]), str(r["output_bytes"]))
        console.print(table)
    if out:
        lines = [f"# autopower profile: {runs} runs on {host.node()} ({host.processor() or host.machine()}), "
                 f"{datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC",
                 "# use: autopower plan SCENARIO --latency-profile THIS_FILE --as-platform PLATFORM", "",
                 "[latency_s]        # median seconds per run"]
        lines += [f"{name} = {r['latency_median_s']:.6g}" for name, r in result.items()]
        lines += ["", "[message_bytes]    # largest input and output seen"]
        lines += [f"{name} = [{r['input_bytes_max']}, {r['output_bytes_max']}]" for name, r in result.items()]
        with open(out, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")
        console.print(f"wrote {out}")


def _register_commands() -> None:
    """Commands that live in their own modules (they import heavier parts lazily)."""
    from autopower.cli.replay import replay
    from autopower.cli.simulate import simulate
    from autopower.cli.team import COMMANDS  # agent, basestation, up, chain, migrate, status

    cli.add_command(simulate)
    cli.add_command(replay)
    for command in COMMANDS:
        cli.add_command(command)


_register_commands()


def main() -> None:
    run_command(cli, prog_name="autopower")


if __name__ == "__main__":
    main()
