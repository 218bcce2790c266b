"""`autopower demo`: the whole story in one command (see `autopower.launch.demo`)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import click

from autopower.cli.options import INSECURE_OPT, warn_insecure
from autopower.errors import AutoPowerError
from autopower.launch.demo import run_demo
from autopower.policies import POLICY_NAMES


@click.command("demo")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (and nothing else on stdout).")
@click.option("--speed", type=float, default=5.0, show_default=True, help="Virtual seconds per wall second.")
@click.option("--mission", "mission_wall_s", type=float, default=35.0, show_default=True,
              help="Wall seconds the planned mission lasts (sets the battery size).")
@click.option("--lease-ms", default=500, show_default=True)
@click.option("--log-dir", type=click.Path(file_okay=False), default=None,
              help="Where logs and the recording go (default: a new temporary directory).")
@click.option("--no-record", is_flag=True, help="Do not write a Rerun recording.")
@click.option("--policy", type=click.Choice(list(POLICY_NAMES)), default="rebalance", show_default=True,
              help="What decides the placement at the base station (as in `autopower simulate`).")
@INSECURE_OPT
@click.option("--testbed", is_flag=True,
              help="Run the story in the testbed (root): network namespaces, links shaped like their radios.")
def demo(as_json, speed, mission_wall_s, lease_ms, log_dir, no_record, policy, insecure, testbed):
    """Three agents + the base station: a cut, a heal, a subgroup without the base, the replay."""
    if not 10 <= mission_wall_s <= 600:
        raise AutoPowerError(f"--mission must be within 10..600 s, got {mission_wall_s:g}")
    if not speed > 0:
        raise AutoPowerError(f"--speed must be > 0, got {speed:g}")
    warn_insecure(insecure)
    directory = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="autopower-demo-"))
    directory.mkdir(parents=True, exist_ok=True)
    result = run_demo(speed=speed, mission_wall_s=mission_wall_s, lease_ms=lease_ms, log_dir=directory,
                      record=not no_record, quiet=as_json, policy=policy,
                      secure=not insecure, testbed=testbed)
    if as_json:
        slim = {k: v for k, v in result.items() if k != "replay"}
        click.echo(json.dumps(slim, default=str))
        return
    click.echo(f"demo finished in {result['wall_s']:.1f} s; logs in {result['log_dir']}")
    for f in result["faults"]:
        click.echo(f"  {f['kind']:<8} {f['target']:<22} detected {f['detected_s'] or float('nan'):.3f} s  "
                   f"reconfigured {f['reconfigured_s']:.3f} s")
    click.echo(f"  migrations {result['migrations']}, lost outputs {result['lost_outputs']}, duplicated "
               f"{result['duplicated_outputs']}, energy model error {result['energy_model_error_pct']}")
    if result.get("recording"):
        click.echo(f"  recording: {result['recording']}  (autopower replay {result['recording']})")
    if result.get("replay"):
        click.echo(json.dumps(result["replay"], indent=1, default=str))


COMMANDS = [demo]
