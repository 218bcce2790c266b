"""`autopower simulate`: a whole mission in virtual time, with events and a reallocation policy.

Register with ``cli.add_command(simulate)``. Errors are `AutoPowerError`s (the CLI prints them and
exits 2).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import click

from autopower.cli.options import build_scenario
from autopower.errors import AutoPowerError
from autopower.policies import POLICY_NAMES

TOPOLOGIES = ["fully-connected", "relay", "explicit"]


def _check_record_path(path: str) -> None:
    target = Path(path)
    folder = target.parent if str(target.parent) else Path(".")
    if target.is_dir():
        raise AutoPowerError(f"--record {path}: is a directory; give a file name such as run.rrd")
    if not folder.is_dir():
        raise AutoPowerError(f"--record {path}: folder {folder} does not exist; create it or pick another path")
    if not os.access(folder, os.W_OK) or (target.exists() and not os.access(target, os.W_OK)):
        raise AutoPowerError(f"--record {path}: not writable; pick a path you can write to")


@click.command("simulate")
@click.argument("scenario", default="paper-fig7", metavar="SCENARIO")
@click.option("--events", "events_name", default=None, metavar="EVENTS",
              help="Events file (.toml) or a built-in name (paper-vc-fault, cameras-off, link-cuts).")
@click.option("--policy", type=click.Choice([*POLICY_NAMES, "all"]), default="rebalance", show_default=True,
              help="Reallocation policy; 'all' runs each and compares them.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the battery-reading noise.")
@click.option("--topology", type=click.Choice(TOPOLOGIES), default=None, help="Topology (default: the scenario's).")
@click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None,
              help="Message accounting (default: the scenario's).")
@click.option("--energy", multiple=True, metavar="ROBOT=J", help="Override a robot's starting energy (repeatable).")
@click.option("--record", type=str, default=None, metavar="RUN.rrd", help="Write a Rerun recording of the run.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of tables.")
def simulate(scenario, events_name, policy, seed, topology, accounting, energy, record, as_json) -> None:
    """Simulate a mission in virtual time until the first robot runs dry.

    Batteries drain per the energy model; events (link cuts, radio faults, chains switched off,
    robots leaving or joining, energy offsets) happen at their times; the policy reallocates and
    every migration is charged. Without events the result is compared with the planner's
    time-sharing upper bound.
    """
    from autopower.model.mission_events import NO_EVENTS, load_events
    from autopower.simulation.simulator import simulate as run, time_sharing_reference

    s = build_scenario(scenario, energy, accounting=accounting)
    script = load_events(events_name, s, topology=topology) if events_name else NO_EVENTS
    policies = list(POLICY_NAMES) if policy == "all" else [policy]
    if record is not None:
        if len(policies) > 1:
            raise AutoPowerError("--record needs one --policy (a recording holds one run); drop --policy all")
        _check_record_path(record)
    bound = best = None
    if not script.events and not script.initially_absent:
        bound, best = time_sharing_reference(s, topology=topology)
    results = []
    telemetry = None
    for name in policies:
        if record is not None:
            from autopower.recording.blueprint import design
            from autopower.recording.telemetry import Telemetry

            telemetry = Telemetry(record, kind="simulation", blueprint=design, properties={
                "scenario": s.name, "policy": name, "seed": seed, "events": script.source_path,
                "accounting": s.accounting, "topology": topology or s.network_spec.topology})
        try:
            results.append(run(s, script, policy=name, seed=seed, topology=topology, telemetry=telemetry))
        finally:
            if telemetry is not None:
                telemetry.close()
    if telemetry is not None and telemetry.errors:
        click.echo(f"warning: {telemetry.errors} telemetry write(s) failed; the recording may be incomplete",
                   err=True)

    def summary(r) -> dict:
        d = r.to_dict()
        if bound is not None:
            d["time_sharing_bound_s"] = bound.lifetime_s
            d["fraction_of_bound"] = r.lifetime_s / bound.lifetime_s if bound.lifetime_s else None
            d["best_static_s"] = best.lifetime_s
        if record is not None:
            d["recording"] = record
            d["recording_id"] = telemetry.recording_id if telemetry else None
        return d

    if as_json:
        if len(results) == 1:
            click.echo(json.dumps(summary(results[0]), indent=2))
        else:
            click.echo(json.dumps({"scenario": s.name, "events": script.source_path,
                                   "policies": {r.policy: summary(r) for r in results}}, indent=2))
        return
    _print(s, script, results, bound, best, record)


def _print(s, script, results, bound, best, record) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console() if sys.stdout.isatty() else Console(width=200)
    head = f"[bold]{s.name}[/bold] ({s.accounting} accounting"
    head += f", events: {script.description or script.source_path})" if script.events else ", no events)"
    console.print(head)
    static = next((r.lifetime_s for r in results if r.policy == "static"), None)
    table = Table("policy", "lifetime s", "end", "vs static", "of bound", "migrations", "migration J",
                  "missed periods", "decisions", "wall s")
    for r in results:
        table.add_row(r.policy, f"{r.lifetime_s:,.1f}", r.end_reason,
                      f"{r.lifetime_s / static - 1:+.2%}" if static else "",
                      f"{r.lifetime_s / bound.lifetime_s:.2%}" if bound and bound.lifetime_s else "",
                      str(len(r.migrations)), f"{r.migration_energy_j:.3f}", str(r.missed_periods),
                      str(len(r.decisions)), f"{r.wall_s:.3f}")
    console.print(table)
    if bound is not None:
        console.print(f"time-sharing bound {bound.lifetime_s:,.1f} s; best static plan {best.lifetime_s:,.1f} s")
    if len(results) == 1:
        r = results[0]
        log = Table("t s", "forced", "moves", "media", "why")
        for d in r.decisions:
            log.add_row(f"{d.time_s:,.1f}", "yes" if d.forced else "", str(d.moves),
                        ", ".join(f"{g}={m}" for g, m in d.media.items()), "\n".join(d.reasons))
        console.print(log)
        if record is not None:
            console.print(f"recording: {record}")


COMMANDS = (simulate,)
