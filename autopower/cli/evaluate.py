"""`autopower evaluate`: the full breakdown of one allocation the user chooses, on any topology.

The JSON object is documented in docs/reference/json-output.md (`evaluate`); `breakdown` builds it
and the text view prints the same figures.
"""

from __future__ import annotations

import json

import click
from rich.table import Table

from autopower.cli.options import (
    ACCOUNTING_OPT,
    CONTROL_PLANE_OPT,
    ENERGY_OPT,
    JSON_OPT,
    SCENARIO_ARG,
    build_scenario,
    console,
    parse_pairs,
)
from autopower.errors import ScenarioError
from autopower.model.dag import active_flows, chain_of_stage
from autopower.model.energy import Evaluation, active_chains, evaluate, flow_rate_hz
from autopower.model.network import Network, build_network, describe_media
from autopower.model.scenario import TOPOLOGIES, Scenario


def placement(scenario: Scenario, network: Network, given: dict[str, str]) -> tuple[dict[str, str], list[str]]:
    """Every active stage's host: the given ones, else the scenario's pin, else the chain's source.

    Returns the allocation and one note per stage that was not given (saying where it went and why).
    """
    stages = [s.name for c in active_chains(scenario, network) for s in c.stages]
    for stage, host in given.items():
        if stage not in stages:
            raise ScenarioError(f"--place {stage}={host}: unknown stage {stage!r}; stages: {', '.join(stages)}")
        if host not in network.nodes:
            raise ScenarioError(f"--place {stage}={host}: unknown node {host!r}; nodes: {', '.join(network.nodes)}")
    allocation, notes = {}, []
    for chain in active_chains(scenario, network):
        for stage in chain.stages:
            if stage.name in given:
                host = given[stage.name]
                if stage.pin and host != stage.pin:
                    notes.append(f"{stage.name}: placed on {host} although the scenario pins it to {stage.pin}")
                elif stage.hosts and host not in stage.hosts:
                    notes.append(f"{stage.name}: placed on {host} although the scenario allows only "
                                 f"{', '.join(stage.hosts)}")
            elif stage.pin:
                host = stage.pin
                notes.append(f"{stage.name}: not given; runs on {host}, where the scenario pins it")
            elif stage.hosts and chain.source not in stage.hosts:
                host = stage.hosts[0]
                notes.append(f"{stage.name}: not given; runs on {host}, the first host the scenario allows "
                             f"(its source {chain.source} is not among them)")
            else:
                host = chain.source
                notes.append(f"{stage.name}: not given; runs at its source {host}")
            allocation[stage.name] = host
    return allocation, notes


def flows(scenario: Scenario, network: Network, allocation: dict[str, str], accounting: str) -> list[dict]:
    """Each message flow of each active chain with its route (hop, medium) and modelled rate."""
    out = []
    for chain in active_chains(scenario, network):
        hops = (chain.source, *(allocation[s.name] for s in chain.stages), chain.sink)
        names = ("source", *(s.name for s in chain.stages), "sink")
        for k, n_bytes in enumerate(chain.message_bytes):
            src, dst = hops[k], hops[k + 1]
            if k == 0 and not chain.sourced:
                continue  # a DAG chain fed by other stages: its inputs are the flows below
            out.append({
                "chain": chain.name, "from_stage": names[k], "to_stage": names[k + 1],
                "from": src, "to": dst, "bytes": n_bytes, "rate_hz": flow_rate_hz(chain, accounting),
                "route": [{"from": u, "to": v, "medium": m} for u, v, m in network.route(src, dst)],
            })
    chains = active_chains(scenario, network)
    by_stage = chain_of_stage(chains)
    for flow in active_flows(chains):  # DAG edges: a stage's output into another chain's stage
        src, dst = allocation[flow.producer], allocation[flow.consumer]
        out.append({
            "chain": by_stage[flow.consumer].name, "flow": flow.name, "from_stage": flow.producer,
            "to_stage": flow.consumer, "from": src, "to": dst, "bytes": flow.n_bytes,
            "rate_hz": flow_rate_hz(by_stage[flow.producer], accounting),
            "route": [{"from": u, "to": v, "medium": m} for u, v, m in network.route(src, dst)]
            if network.reachable(src, dst) else [],
        })
    return out


def breakdown(scenario: Scenario, network: Network, ev: Evaluation, notes: list[str]) -> dict:
    return {
        "scenario": scenario.name,
        "accounting": ev.accounting,
        "topology": network.topology,
        "media": network.media_by_group(),
        "links": [{"a": l.a, "b": l.b, "medium": l.medium, "group": l.group} for l in network.links],
        "allocation": dict(ev.allocation),
        "notes": notes,
        "feasible": ev.feasible,
        "lifetime_s": ev.lifetime_rounded_s,
        "lifetime_raw_s": ev.lifetime_s,
        "rounding_s": scenario.lifetime_rounding_s,
        "bottleneck": ev.bottleneck,
        "robots": {
            name: {
                "energy_j": rp.energy_j,
                "power_w": rp.total_w,
                "cpu_w": rp.cpu_w,
                "cpu_util": rp.cpu_utilisation,
                "control_w": rp.control_w,
                "lifetime_raw_s": rp.lifetime_s,
                "radios": {m: {"busy": r.busy, "power_w": r.total_w, "send_w": r.send_w,
                               "receive_w": r.receive_w, "sleep_w": r.sleep_w} for m, r in rp.radios.items()},
            }
            for name, rp in ev.robots.items()
        },
        "basestation": {
            "name": network.basestation,
            "cpu_util": ev.utilisation.get(network.basestation, 0.0),
            "radios_limited": scenario.basestation_radio_limit,
            "radios": {m: {"busy": busy} for m, busy in ev.basestation_radio_busy.items()},
        },
        "violations": [v.to_dict() for v in ev.violations],
        "flows": flows(scenario, network, dict(ev.allocation), ev.accounting),
    }


@click.command("evaluate")
@SCENARIO_ARG
@click.option("--place", multiple=True, metavar="STAGE=NODE",
              help="Run STAGE on NODE (repeatable); stages not given stay at their pin, else at their source.")
@click.option("--media", multiple=True, metavar="GROUP=MEDIUM",
              help="A link group's medium, e.g. laptop-robot=gsm (default: each group's first candidate).")
@click.option("--topology", type=click.Choice(TOPOLOGIES), default=None, help="Default: the scenario's.")
@ENERGY_OPT
@ACCOUNTING_OPT
@CONTROL_PLANE_OPT
@JSON_OPT
def evaluate_cmd(scenario, place, media, topology, energy, accounting, control_plane, as_json) -> None:
    """Score one allocation: power, CPU and radio load per robot, lifetime, violations, routes."""
    s = build_scenario(scenario, energy, accounting=accounting, control_plane=control_plane)
    network = build_network(s, topology, parse_pairs(media, "--media", "laptop-robot=gsm"))
    allocation, notes = placement(s, network, parse_pairs(place, "--place", "Loc-1=laptop"))
    ev = evaluate(s, network, allocation)
    result = breakdown(s, network, ev, notes)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    _print(result)


def _print(r: dict) -> None:
    console.print(f"[bold]{r['scenario']}[/bold] ({r['accounting']} accounting, {r['topology']}, "
                  f"media {describe_media(r['media'])})")
    console.print("allocation: " + ", ".join(f"{s}→{h}" for s, h in r["allocation"].items()))
    for note in r["notes"]:
        console.print(f"  note: {note}")
    if r["feasible"]:
        console.print(f"lifetime [bold green]{r['lifetime_s']:.1f} s[/bold green] (raw {r['lifetime_raw_s']:.3f} s, "
                      f"rounded to {r['rounding_s']:g} s), bottleneck {r['bottleneck']}")
    else:
        console.print(f"[bold red]infeasible[/bold red]: {len(r['violations'])} limit(s) exceeded")
    charged = any(rp["control_w"] for rp in r["robots"].values())  # `--control-plane`: its own column
    table = Table("robot", "energy J", "power W", "CPU W", "CPU util", "radios (busy, W)",
                  *(["of which control W"] if charged else []), "lifetime s (raw)")
    for name, rp in r["robots"].items():
        radios = ", ".join(f"{m} {x['busy']:.1%} {x['power_w']:.4f} W" for m, x in rp["radios"].items())
        table.add_row(name, f"{rp['energy_j']:g}", f"{rp['power_w']:.4f}", f"{rp['cpu_w']:.4f}",
                      f"{rp['cpu_util']:.1%}", radios, *([f"{rp['control_w']:.4f}"] if charged else []),
                      f"{rp['lifetime_raw_s']:.1f}")
    console.print(table)
    base = r["basestation"]
    console.print(f"{base['name']} (base station): CPU {base['cpu_util']:.1%}; radios "
                  + (", ".join(f"{m} {x['busy']:.1%} busy" for m, x in base["radios"].items()) or "none")
                  + ("" if base["radios_limited"] else " (not limited)"))
    for v in r["violations"]:
        console.print(f"[red]violation[/red]: {v['message']}")
    routes = Table("chain", "flow", "bytes", "msg/s", "route")
    for f in r["flows"]:
        route = " ".join(f"{h['from']} -{h['medium']}→ {h['to']}" for h in f["route"]) or f"{f['from']} (local)"
        routes.add_row(f["chain"], f"{f['from_stage']} → {f['to_stage']}", str(f["bytes"]), f"{f['rate_hz']:g}", route)
    console.print(routes)


COMMANDS = (evaluate_cmd,)
