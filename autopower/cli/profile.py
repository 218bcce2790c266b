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
        click.echo(f"wrote {out}", err=as_json)


COMMANDS = (profile,)
