"""`scenarios`: list the built-in scenarios, or generate one (`scenarios fleet N`)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from autopower.cli.options import console
from autopower.errors import ScenarioError
from autopower.model.loading import builtin_scenarios, load_scenario


@click.group("scenarios", invoke_without_command=True)
@click.pass_context
def scenarios(ctx: click.Context) -> None:
    """List the built-in scenarios; `scenarios fleet N` writes a fleet of N robots."""
    if ctx.invoked_subcommand is None:
        for name in builtin_scenarios():
            console.print(f"{name}: {load_scenario(name).description}")


@scenarios.command("fleet")
@click.argument("robots", type=int, metavar="N")
@click.option("--cameras", type=int, default=None, metavar="K",
              help="How many robots carry a camera (and run a Blob chain)  [default: all N]")
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "neighbours"]), default="fully-connected",
              show_default=True, help="The topology planned (relay: r1 links to the base station; neighbours: "
                                      "every robot to the base station and to its ring neighbours).")
@click.option("--neighbours", type=click.IntRange(min=1), default=1, show_default=True, metavar="K",
              help="With --topology neighbours: the robots in range on either side of each robot in the ring.")
@click.option("--medium", "media", multiple=True, metavar="MEDIUM",
              help="A candidate medium of every link, of the paper's radios: 802.11a, bluetooth, gsm "
                   "(repeatable; the first is the default)  [default: the paper's per link group]")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Which robots carry the cameras when K < N.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="FILE",
              help="Write the scenario to FILE (default: print it on stdout).")
@click.option("--json", "as_json", is_flag=True,
              help="Print one JSON object (path, robots, chains, stages, topology, ...) instead of a line (needs --out).")
def fleet(robots: int, cameras: int | None, topology: str, neighbours: int, media: tuple[str, ...], seed: int,
          out: Path | None, as_json: bool) -> None:
    """Write a scenario of N robots running the paper's mission (paper-fig7), checked by the loader.

    Every robot is the paper's: its platform, battery, radios, a laser and odometry, and K of them
    a camera. Each runs a Loc chain, each with a camera a 4 Hz Blob chain to the operator; the
    base station and the components are the paper's. Without --out the TOML goes to stdout.
    """
    from autopower.simulation.synthetic import paper_fleet

    if as_json and out is None:
        raise ScenarioError("--json prints a summary, not the scenario: give --out FILE for the scenario")
    text, scenario = paper_fleet(robots, cameras, topology=topology, media=media, seed=seed,
                                 neighbours=neighbours)
    if out is None:
        click.echo(text, nl=False)
        return
    try:
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ScenarioError(f"{out}: cannot write it ({exc.strerror or exc}); check the path and permissions") from None
    summary = {"path": str(out), "scenario": scenario.name, "robots": len(scenario.robots),
               "cameras": sum("camera" in r.sensors for r in scenario.robots), "chains": len(scenario.chains),
               "stages": len(scenario.stage_names()), "topology": scenario.network_spec.topology,
               "links": link_count(scenario),
               "media": media_by_group(scenario)}
    if as_json:
        click.echo(json.dumps(summary, indent=2))
        return
    console.print(f"[green]wrote[/green] {out}: {scenario.name} — {summary['robots']} robots "
                  f"({summary['cameras']} with a camera), {summary['chains']} chains, {summary['stages']} stages, "
                  f"{summary['topology']}")


def media_by_group(scenario) -> dict[str, list[str]]:
    """Each link group's candidate media, as the scenario's topology lays its links out."""
    links, cliques = scenario.link_layout()
    return {spec.group: list(spec.media) for spec in (*links, *cliques)}


def link_count(scenario) -> int:
    """The topology's links, a clique's pairs counted without building them."""
    links, cliques = scenario.link_layout()
    return len(links) + sum(len(c.nodes) * (len(c.nodes) - 1) // 2 for c in cliques)


COMMANDS = (scenarios,)
