"""`autopower demo`: the whole story in one command (see `autopower.launch.demo`)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import click

from autopower.cli.options import INSECURE_OPT, LEASE_MS, POSITIVE, TRANSPORT_OPT, stage_workers_option, warn_insecure
from autopower.errors import AutoPowerError
from autopower.launch.demo import run_demo
from autopower.policies import POLICY_NAMES


@click.command("demo")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (and nothing else on stdout).")
@click.option("--speed", type=POSITIVE, default=5.0, show_default=True, help="Virtual seconds per wall second.")
@click.option("--mission", "mission_wall_s", type=POSITIVE, default=35.0, show_default=True,
              help="Wall seconds the planned mission lasts (sets the battery size).")
@click.option("--lease-ms", default=500, show_default=True, type=LEASE_MS)
@click.option("--log-dir", type=click.Path(file_okay=False), default=None,
              help="Where logs and the recording go (default: a new temporary directory).")
@click.option("--no-record", is_flag=True, help="Do not write a Rerun recording.")
@click.option("--policy", type=click.Choice(list(POLICY_NAMES)), default="rebalance", show_default=True,
              help="What decides the placement at the base station (as in `autopower simulate`).")
@INSECURE_OPT
@click.option("--testbed", is_flag=True,
              help="Run the story in the testbed (root): network namespaces, links shaped like their radios.")
@click.option("--crash-basestation/--no-crash-basestation", "crash_base", default=True, show_default=True,
              help="SIGKILL the base station after the agent: the robots carry on in a subgroup, the "
                   "supervisor starts a new base station and it takes over the running team.")
@stage_workers_option
@TRANSPORT_OPT
def demo(as_json, speed, mission_wall_s, lease_ms, log_dir, no_record, policy, insecure, testbed, crash_base,
         stage_workers, transport):
    """Three agents + the base station: a cut, a heal, a subgroup without the base, an agent and the
    base station killed and restarted, the replay."""
    if not 10 <= mission_wall_s <= 600:
        raise AutoPowerError(f"--mission must be within 10..600 s, got {mission_wall_s:g}")
    if not speed > 0:
        raise AutoPowerError(f"--speed must be > 0, got {speed:g}")
    if insecure and testbed:
        raise AutoPowerError("--insecure does not apply to --testbed: the testbed always runs mutual TLS and "
                             "access control; drop --insecure")
    if transport != "tls" and not testbed:
        raise AutoPowerError(f"--transport {transport} needs --testbed: on localhost the demo's links are proxies "
                             "that forward TCP (they stand for the radios a fault cuts)")
    warn_insecure(insecure)
    directory = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix="autopower-demo-"))
    directory.mkdir(parents=True, exist_ok=True)
    result = run_demo(speed=speed, mission_wall_s=mission_wall_s, lease_ms=lease_ms, log_dir=directory,
                      record=not no_record, quiet=as_json, policy=policy,
                      secure=not insecure, testbed=testbed, crash_base=crash_base, stage_workers=stage_workers,
                      transport=transport)
    if as_json:
        slim = {k: v for k, v in result.items() if k != "replay"}  # the full replay: `autopower replay`
        click.echo(json.dumps(slim, default=str))
        return
    click.echo(human_summary(result))


def _secs(x: float | None, digits: int = 2) -> str:
    return "—" if x is None else f"{x:.{digits}f} s"


def human_summary(result: dict) -> str:
    """A few readable lines: what happened, rounded to what matters."""
    source = "the replay of its recording" if result["source"] == "recording" else "live measurements"
    lines = [f"demo finished in {result['wall_s']:.0f} s (summary from {source}; logs in {result['log_dir']})"]
    for f in result["faults"]:
        parts = f["parts"]
        what = f"{f['kind']} {parts[0]}" if len(parts) == 1 else f"{f['kind']} {', '.join(parts)} together"
        how = (f["reconfigured_by"] or "").split(" ")[0]
        done = "subgroup committed" if how == "subgroup" else "reconfigured"
        mission = ""
        if f.get("detected_mission_s") is not None and f.get("reconfigured_mission_s") is not None:
            mission = f"; mission time {f['detected_mission_s']:.1f} s, {f['reconfigured_mission_s']:.1f} s"
        after = "the SIGKILL" if f["kind"].startswith("crash-") else "the cut"
        line = (f"  {what}: detected {_secs(f['detected_wall_s'])}, {done} {_secs(f['reconfigured_wall_s'])} "
                f"after {after} (wall clock{mission})")
        if f.get("restarted_wall_s") is not None:
            line += f"; restarted {_secs(f['restarted_wall_s'])}"
        if f.get("rejoined_wall_s") is not None:
            line += f", back with its chains {_secs(f['rejoined_wall_s'])}"
        if f.get("battery_before_j") is not None and f.get("battery_after_j") is not None:
            line += f" (battery {f['battery_before_j']:,.0f} J -> {f['battery_after_j']:,.0f} J: not reset)"
        if f["kind"] == "crash-basestation":
            line += (f", new base station took over {_secs(f['taken_over_wall_s'])}" if f.get("taken_over_wall_s")
                     is not None else ", the new base station did not take over the running team in time")
        lines.append(line)
    outputs = f"{result['outputs']} outputs, " if result.get("outputs") is not None else ""
    lines.append(f"  {result['migrations']} migrations; {outputs}{result['lost_outputs']} lost, "
                 f"{result['duplicated_outputs']} duplicated")
    error = result.get("energy_model_error_pct")
    if error is not None:
        # what the model leaves out, set apart before the comparison and said (not hidden in it)
        apart = [f"{what} {result[key]:.0f} J" for what, key in (("recovery after the cuts", "recovery_j"),
                                                                  ("backlogs of restarted stages", "backlog_j"),
                                                                  ("the runtime's own CPU", "runtime_j"),
                                                                  ("the control plane", "control_j"))
                 if result.get(key)]
        steady, shifted = result.get("energy_steady_error_pct"), result.get("transition_j")
        lines.append(f"  energy: metered within {abs(error):.1f} % of the model"
                     + (f", {abs(steady):.1f} % outside reconfigurations (they shifted {shifted:+.1f} J)"
                        if steady is not None and shifted is not None else "")
                     + (f" (set apart: {', '.join(apart)})" if apart else ""))
    dry = result.get("first_dry")
    if dry:
        lines.append(f"  first to run dry: {dry['robot']} at {dry['at_s']:.0f} s mission time"
                     + (" (projected)" if dry.get("projected") else ""))
    if result.get("recording"):
        lines.append(f"  recording: {result['recording']}")
        lines.append(f"  full story: autopower replay {result['recording']}")
    elif result.get("recording_error"):
        lines.append(f"  recording unavailable: {result['recording_error']}")
    return "\n".join(lines)


COMMANDS = [demo]
