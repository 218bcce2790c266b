"""`autopower profile`: measure the real components on this machine."""

from __future__ import annotations

import json

import click
from rich.table import Table

from autopower.cli.options import JSON_OPT, console
from autopower.errors import AutoPowerError


@click.command("profile")
@click.option("--runs", default=50, show_default=True, help="Runs per component.")
@click.option("--out", default=None, metavar="FILE", help="Write the profile (TOML) here.")
@click.option("--component", "component_path", default=None, metavar="PKG.MOD:CLASS",
              help="Measure a component of your own instead (prints its [components.X] block).")
@click.option("--source", "source_path", default=None, metavar="PKG.MOD:CLASS",
              help="The source that feeds --component (default: the component class's SOURCE).")
@click.option("--name", default=None, help="Component type name for the block (default: the class name).")
@click.option("--factor", multiple=True, metavar="PLATFORM=X",
              help="Platform latency = measured x X (repeatable; default laptop=1 sitsang=50).")
@JSON_OPT
def profile(runs: int, out: str | None, component_path: str | None, source_path: str | None, name: str | None,
            factor: tuple[str, ...], as_json: bool) -> None:
    """Measure each real component's latency and message sizes on this machine.

    The file it writes plugs into any scenario: `autopower plan --latency-profile FILE
    --as-platform laptop` plans as if the base station were this machine.

    With --component (and --source), measure your own component instead: latency, output and
    state size, and print the [components.X] block to paste into a scenario.
    """
    import platform as host
    from datetime import datetime, timezone

    from autopower.chains.profile import profile_components

    if component_path is not None or source_path is not None:
        _profile_plugin(component_path, source_path, name, factor, runs, as_json)
        return
    if runs < 1:
        raise AutoPowerError(f"--runs must be >= 1, got {runs}")
    from autopower.runtime.memory import keep_large_buffers

    keep_large_buffers()  # measured with the allocator the team's processes run with
    result = profile_components(runs)
    if as_json:
        click.echo(json.dumps(result, indent=2))
    else:
        table = Table("component", "mean ms", "median ms", "max ms", "input B", "output B", title=f"{runs} runs on this machine")
        for name, r in result.items():
            table.add_row(name, f"{r['latency_mean_s'] * 1e3:.3f}", f"{r['latency_median_s'] * 1e3:.3f}",
                          f"{r['latency_max_s'] * 1e3:.3f}", str(r["input_bytes"]), str(r["output_bytes"]))
        console.print(table)
        _print_limit(result)
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
        click.echo(f"wrote {out}", err=as_json)


def _print_limit(result) -> None:
    """How fast the default mission (paper-fig7) could run live here at best (docs/performance.md)."""
    import os

    from autopower.chains.profile import live_limit
    from autopower.cli.options import build_scenario

    scenario = build_scenario("paper-fig7")
    if not all(stage.component in result for chain in scenario.chains for stage in chain.stages):
        return
    cores = os.cpu_count() or 1
    need, limit = live_limit(scenario, result, cores)
    console.print(f"live limit of {scenario.name} here: its components need {need * 1e3:.2f} ms of CPU per virtual "
                  f"second -> x{limit:.0f} on {cores} cores (nothing left for the runtime at that speed-up)")


def _profile_plugin(component_path, source_path, name, factor, runs, as_json) -> None:
    from autopower.chains.plugins import check_component_class, check_source_class, load_class
    from autopower.chains.profile import DEFAULT_PLATFORM_FACTORS, components_block, profile_plugin
    from autopower.cli.options import parse_pairs

    if component_path is None:
        raise AutoPowerError("--source needs --component PKG.MOD:CLASS (the component it feeds)")
    if runs < 1:
        raise AutoPowerError(f"--runs must be >= 1, got {runs}")
    factors = dict(DEFAULT_PLATFORM_FACTORS)
    if factor:
        factors = {}
        for platform, value in parse_pairs(factor, "--factor", "sitsang=50").items():
            try:
                factors[platform] = float(value)
            except ValueError:
                factors[platform] = float("nan")
            if not factors[platform] > 0:
                raise AutoPowerError(f"--factor {platform}={value}: expected a number > 0")
    component_cls = load_class(component_path, "--component")
    check_component_class(component_cls, f"--component {component_path}")
    if source_path is None:
        source = getattr(component_cls, "SOURCE", None)
        if source is None:
            raise AutoPowerError(f"--component {component_path}: give --source PKG.MOD:CLASS (the class has no "
                                 f"SOURCE attribute naming its source)")
        source_path = source if isinstance(source, str) else f"{source.__module__}:{source.__qualname__}"
    source_cls = load_class(source_path, "--source")
    check_source_class(source_cls, f"--source {source_path}")
    try:
        measured = profile_plugin(component_cls, source_cls, runs)
    except Exception as exc:  # the user's code failed while being measured: say so in one line
        raise AutoPowerError(f"profiling {component_path} failed: {type(exc).__name__}: {exc}") from None
    name = name or component_cls.__name__
    block = components_block(name, component_path, source_path, measured, factors)
    if as_json:
        click.echo(json.dumps({"name": name, "component": component_path, "source": source_path,
                               "platform_factors": factors, "measured": measured,
                               "latency_s": {p: measured["latency_median_s"] * f for p, f in factors.items()},
                               "block": block}, indent=2))
        return
    click.echo(f"# {name}: {runs} runs on this machine: median {measured['latency_median_s'] * 1e3:.3f} ms "
               f"(mean {measured['latency_mean_s'] * 1e3:.3f}, max {measured['latency_max_s'] * 1e3:.3f}); output "
               f"{measured['output_bytes_max']} B, state {measured['state_bytes_max']} B "
               f"(export {measured['export_s'] * 1e3:.3f} ms, import {measured['import_s'] * 1e3:.3f} ms)",
               err=True)
    click.echo(block)


COMMANDS = (profile,)
