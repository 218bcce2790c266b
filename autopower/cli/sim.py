"""`autopower sim`: the team's real cores on a simulated network and clock, faults drawn from a seed.

Register with ``cli.add_command(sim)``. Bad input is an `AutoPowerError` (exit 2); a violated
invariant is exit 3, after the run's report.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
from pathlib import Path

import click

from autopower.cli.options import NON_NEGATIVE, POSITIVE, build_scenario
from autopower.errors import AutoPowerError

VIOLATED = 3  # the exit status of a run that violated an invariant
REPLAY_VERSION = 1


@contextlib.contextmanager
def _logs(level: str | None):
    """The cores' logs at ``level`` on stderr, or none (the verdict and the trace say what happened)."""
    if level is None:
        logging.disable(logging.CRITICAL)
        try:
            yield
        finally:
            logging.disable(logging.NOTSET)
    else:
        from autopower.cli.options import setup_logging

        setup_logging(level)
        yield


def _read_replay(path: str) -> dict:
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise AutoPowerError(f"--replay {path}: no such file") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise AutoPowerError(f"--replay {path}: not a saved run ({exc})") from None
    if not isinstance(doc, dict) or doc.get("autopower_sim") != REPLAY_VERSION:
        raise AutoPowerError(f"--replay {path}: not a run saved by `autopower sim --save` (version "
                             f"{REPLAY_VERSION})")
    for key, kind in (("scenario", str), ("seed", int), ("mission_s", (int, float)), ("quiet_s", (int, float)),
                      ("faults", list)):
        if not isinstance(doc.get(key), kind) or isinstance(doc.get(key), bool):
            raise AutoPowerError(f"--replay {path}: {key!r} is missing or not a {getattr(kind, '__name__', 'number')}")
    return doc


def _saved(scenario: str, config, kinds, result) -> dict:
    return {"autopower_sim": REPLAY_VERSION, "scenario": scenario, "seed": config.seed,
            "mission_s": config.mission_s, "quiet_s": config.quiet_s, "components": config.components,
            "kinds": list(kinds), "faults": [f.to_json() for f in config.faults],
            "violations": [v.to_json() for v in result.violations], "trace_sha256": result.trace_sha256}


def _write(path: str, doc: dict, what: str) -> None:
    try:
        Path(path).write_text(json.dumps(doc, indent=1) + "\n")
    except OSError as exc:
        raise AutoPowerError(f"{what} {path}: cannot write ({exc.strerror or exc})") from None


@click.command("sim")
@click.argument("scenario", required=False, metavar="[SCENARIO]")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="The seed: it draws the fault schedule and every network draw.")
@click.option("--faults", "n_faults", type=click.IntRange(min=0, max=10_000), default=5, show_default=True,
              help="How many faults over the mission.")
@click.option("--mission", "mission_s", type=POSITIVE, default=120.0, show_default=True,
              help="Simulated seconds during which faults happen (from 10 s on).")
@click.option("--quiet", "quiet_s", type=NON_NEGATIVE, default=40.0, show_default=True,
              help="Simulated seconds after the mission with no fault: everything heals, then the run is judged.")
@click.option("--kinds", default=None, metavar="KIND,...",
              help="The fault kinds a seed may enable (default: all of cut, cut-one-way, partition, loss, "
                   "duplicate, reorder, crash, freeze, basestation-crash, migrate, toggle, flap, roam, rate).")
@click.option("--components", type=click.Choice(["stand-in", "real"]), default="stand-in", show_default=True,
              help="Cheap deterministic stand-ins, or the scenario's real components.")
@click.option("--save", "save", default=None, metavar="FILE", help="Write the run (seed, schedule, verdict) to FILE.")
@click.option("--replay", "replay", default=None, metavar="FILE",
              help="Run a saved run again (its scenario, seed and schedule; --seed, --faults, --mission, "
                   "--quiet and --kinds are ignored).")
@click.option("--shrink", "do_shrink", is_flag=True,
              help="If the run fails: shrink its schedule to the smallest that still fails the same way and "
                   "write it to --save FILE (default sim-SEED-shrunk.json).")
@click.option("--trace", "trace_path", default=None, metavar="FILE",
              help="Write the trace (one line per delivered message and fault) to FILE.")
@click.option("--log-level", default=None, type=click.Choice(["debug", "info", "warning", "error"]),
              help="Show the cores' logs on stderr (default: none).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a summary.")
def sim(scenario, seed, n_faults, mission_s, quiet_s, kinds, components, save, replay, do_shrink, trace_path,
        log_level, as_json) -> None:
    """Simulate the team's real cores on a seeded network, with faults, and judge the run.

    The base station's coordinator and every node's runtime run in one process, in simulated time,
    on a network built from the scenario's links. The seed draws the faults (a random subset of
    the kinds, then --faults of them over the mission) and every loss, duplicate and delay. After
    the quiet phase the oracle checks: every output delivered exactly once (or let go by design),
    energy parts adding up, one leader, every node on the newest plan. The same seed gives the
    same trace hash.

    Exit status: 0 when every invariant holds, 3 when one is violated, 2 for bad input.
    """
    from autopower.teamsim import KINDS, Fault, SimConfig, draw, run
    from autopower.teamsim.faults import check_targets

    if replay is not None:
        doc = _read_replay(replay)
        scenario = scenario or doc["scenario"]
        seed, mission_s, quiet_s = doc["seed"], float(doc["mission_s"]), float(doc["quiet_s"])
        components = doc.get("components", components)
        if components not in ("stand-in", "real"):
            raise AutoPowerError(f"--replay {replay}: components {components!r} is neither stand-in nor real")
        faults = [Fault.from_json(f) for f in doc["faults"]]
        enabled = tuple(doc.get("kinds", ()))
    scenario = scenario or "paper-fig7"
    s = build_scenario(scenario, to_run=components == "real")
    if replay is None:
        allowed = tuple(KINDS)
        if kinds is not None:
            allowed = tuple(k.strip() for k in kinds.split(",") if k.strip())
            unknown = [k for k in allowed if k not in KINDS]
            if unknown or not allowed:
                raise AutoPowerError(f"--kinds: unknown kind(s) {', '.join(unknown) or '(none given)'}; kinds: "
                                     f"{', '.join(KINDS)}")
        enabled, faults = draw(s, seed, n_faults, mission_s, allowed)
    check_targets(s, faults)
    config = SimConfig(scenario=s, seed=seed, faults=tuple(faults), mission_s=mission_s, quiet_s=quiet_s,
                       components=components, keep_trace=trace_path is not None)
    with _logs(log_level):
        result = run(config)
        out = {"scenario": s.name, "mission_s": mission_s, "quiet_s": quiet_s, "components": components,
               "kinds": list(enabled), **result.to_json()}
        if trace_path is not None:
            _write_lines(trace_path, result.trace)
            out["trace"] = trace_path
        if save is not None and not (do_shrink and not result.ok):
            _write(save, _saved(scenario, config, enabled, result), "--save")
            out["saved"] = save
        if do_shrink and not result.ok:
            out["shrunk"] = _shrink(scenario, config, enabled, result, save or f"sim-{seed}-shrunk.json", as_json)
    if as_json:
        click.echo(json.dumps(out, indent=1))
    else:
        _print(out)
    if not result.ok:
        sys.exit(VIOLATED)


def _write_lines(path: str, lines: list[str]) -> None:
    try:
        Path(path).write_text("".join(line + "\n" for line in lines))
    except OSError as exc:
        raise AutoPowerError(f"--trace {path}: cannot write ({exc.strerror or exc})") from None


def _shrink(scenario: str, config, enabled, result, path: str, quiet: bool) -> dict:
    import dataclasses

    from autopower.teamsim.shrink import shrink

    invariant = result.violations[0].invariant

    def said(n, faults, bad) -> None:
        if not quiet:
            click.echo(f"shrinking: run {n}: {len(faults)} fault(s): {'fails' if bad else 'passes'}", err=True)

    faults, shrunk = shrink(config, invariant, on_try=said)
    small = dataclasses.replace(config, faults=tuple(faults))
    _write(path, _saved(scenario, small, enabled, shrunk or result), "--save")
    return {"invariant": invariant, "faults": [f.to_json() for f in faults],
            "violations": [v.to_json() for v in (shrunk or result).violations], "file": path}


def _print(out: dict) -> None:
    verdict = "ok" if out["ok"] else f"{len(out['violations'])} violation(s)"
    click.echo(f"{out['scenario']} seed {out['seed']}: {verdict}; trace {out['trace_sha256'][:16]}; "
               f"{out['events']} events, {out['virtual_s']:.1f} mission s in {out['wall_s']:.2f} s")
    decisions, per = out["decisions"], out["per_robot_per_s"]
    mean_ms = 1e3 * decisions["seconds"] / decisions["count"] if decisions["count"] else 0.0
    unproven = decisions.get("not_proven", 0)
    gap = decisions.get("not_proven_max_gap")
    click.echo(f"{out['robots']} robots; {decisions['count']} decisions (policy: {mean_ms:.0f} ms mean, "
               f"{1e3 * decisions['max_s']:.0f} ms max, wall"
               + (f"; {unproven} not proven optimal" + (f", MILP gap up to {gap:.2%} over the hosts searched" if gap is not None else "")
                  if unproven else "")
               + "); sent per robot per mission s: control "
               f"{per['control']['messages']:g} messages ({per['control']['bytes']:,.0f} B), data "
               f"{per['data']['messages']:g} ({per['data']['bytes']:,.0f} B)")
    click.echo(f"fault kinds: {', '.join(out['kinds']) or 'none'}")
    from autopower.teamsim import Fault

    for f in out["faults"]:
        click.echo(f"  {Fault.from_json(f).describe()}")
    click.echo(f"{'chain':<10} {'produced':>9} {'delivered':>10} {'lost':>6} {'duplicated':>11} {'by budget':>10}")
    for name, c in out["chains"].items():
        click.echo(f"{name:<10} {c['produced']:>9} {c['delivered']:>10} {c['lost']:>6} {c['duplicated']:>11} "
                   f"{c['dropped_by_budget']:>10}")
    for v in out["violations"]:
        click.echo(f"VIOLATED {v['invariant']} at {v['t']:.3f} s (trace event {v['event']}): {v['detail']}")
    if "shrunk" in out:
        click.echo(f"shrunk to {len(out['shrunk']['faults'])} fault(s): {out['shrunk']['file']} "
                   f"(autopower sim --replay {out['shrunk']['file']})")
    elif "saved" in out:
        click.echo(f"saved: {out['saved']} (autopower sim --replay {out['saved']})")


COMMANDS = (sim,)
