"""``autopower replay RUN.rrd``: summary, invariant checks, offline what-if, web viewer.

Register with ``cli.add_command(replay)``. A missing, empty, corrupt, truncated or foreign file
is a `RecordingError` (one line on stderr, exit 2, through ``cli.main``); the JSON schema is in
`autopower.recording.replay`'s docstring.
"""

from __future__ import annotations

import json
import math
import signal
import socket
import subprocess
import time
from pathlib import Path

import click

from autopower.cli.entry import run_command
from autopower.cli.options import NON_NEGATIVE, POSITIVE
from autopower.errors import AutoPowerError

__all__ = ["replay", "serve_recording", "main"]


def _energy(values: tuple[str, ...]) -> dict[str, float]:
    out = {}
    for item in values:
        robot, sep, joules = item.partition("=")
        try:
            if not sep or not robot:
                raise ValueError
            out[robot] = float(joules)
        except ValueError:
            raise AutoPowerError(f"--energy {item!r}: expected ROBOT=JOULES, e.g. --energy r1=32000") from None
    return out


def _json_safe(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


@click.command("replay")
@click.argument("recording", metavar="RUN.rrd", type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object (schema: autopower.recording.replay).")
@click.option("--what-if", "whatif", is_flag=True, help="Replan offline from the recorded state (see --at).")
@click.option("--at", "at_s", type=NON_NEGATIVE, default=None, metavar="SECONDS",
              help="Mission time of the state to replan from (default: the end of the recording).")
@click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None,
              help="What-if: message accounting.")
@click.option("--energy", multiple=True, metavar="ROBOT=J", help="What-if: a robot's energy then (repeatable).")
@click.option("--policy", type=click.Choice(["static", "reactive", "rebalance", "subgroup"]), default=None,
              help="What-if: also simulate this policy from the recorded state.")
@click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None,
              help="What-if: plan on this topology (default: the recorded network).")
@click.option("--disable", multiple=True, metavar="CHAIN", help="What-if: switch a chain off (repeatable).")
@click.option("--control-plane/--no-control-plane", "control_plane", default=None,
              help="What-if: charge the team's own statuses and keep-alives on every link (default: as the "
                   "scenario says); the recorded allocation's lifetime and the best plan both change.")
@click.option("--serve", is_flag=True, help="Open the Rerun web viewer on the file (bound to 127.0.0.1, WebGL: "
                                           "works without a GPU); prints its URL.")
@click.option("--serve-seconds", type=POSITIVE, default=None, metavar="S",
              help="With --serve: stop the viewer after S seconds (default: at Ctrl-C).")
def replay(recording, as_json, whatif, at_s, accounting, energy, policy, topology, disable, control_plane, serve,
           serve_seconds) -> None:
    """Summarise a recorded run (simulated or live), check its invariants, replan what-ifs, view it."""
    from autopower.recording.replay import load, summarize
    from autopower.recording.report import render_text
    from autopower.recording.what_if import what_if

    energies = _energy(energy)
    if not whatif and (at_s is not None or accounting or energies or policy or topology or disable
                       or control_plane is not None):
        raise AutoPowerError("--at, --accounting, --energy, --policy, --topology, --disable and --control-plane "
                             "need --what-if")
    rec = load(recording)
    summary = summarize(rec, recording)
    if whatif:
        summary["what_if"] = what_if(rec, at_s=at_s, accounting=accounting, energies=energies, policy=policy,
                                     topology=topology, disable=tuple(disable), control_plane=control_plane)
    if as_json:
        click.echo(json.dumps(_json_safe(summary), sort_keys=False))
    else:
        click.echo(render_text(summary))
    if serve:
        serve_recording(recording, seconds=serve_seconds, echo=lambda m: click.echo(m, err=as_json))


# ---------------------------------------------------------------------------------------------
# --serve
# ---------------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


class _Stop(Exception):
    pass


def serve_recording(path: str | Path, *, seconds: float | None = None, echo=print,
                    ready_timeout_s: float = 20.0) -> int:
    """Serve `path` in the Rerun web viewer on 127.0.0.1 until Ctrl-C/SIGTERM or `seconds`; returns the
    viewer's exit status. The viewer is stopped by its own pid (SIGTERM, then SIGKILL after 5 s)."""
    from autopower.recording.merge import rerun_binary, rerun_env

    web, grpc = _free_port(), _free_port()
    cmd = [rerun_binary(), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
           "--port", str(grpc), str(path)]
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=rerun_env())

    def on_signal(signum, _frame):
        raise _Stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        deadline = time.monotonic() + ready_timeout_s
        while not _listening(web):
            if proc.poll() is not None:
                raise AutoPowerError(f"{path}: the Rerun viewer exited at once (status {proc.returncode}); "
                                     f"try 'rerun rrd verify {path}'")
            if time.monotonic() > deadline:
                raise AutoPowerError(f"the Rerun viewer did not listen on 127.0.0.1:{web} within "
                                     f"{ready_timeout_s:.0f} s")
            time.sleep(0.05)
        # WebGL: the viewer's default WebGPU renderer fails on a machine without a GPU (a server,
        # a VM); WebGL runs anywhere, in software if need be
        url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy&renderer=webgl"
        echo(f"viewer: {url}  (pid {proc.pid}; Ctrl-C to stop)")
        end = None if seconds is None else time.monotonic() + seconds
        while proc.poll() is None:
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                break
            try:
                proc.wait(timeout=0.2 if left is None else min(0.2, left))
            except subprocess.TimeoutExpired:
                pass
    except _Stop:
        pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=5.0)
        echo("viewer stopped")
    return proc.returncode


COMMANDS = (replay,)


def main(argv: list[str] | None = None) -> None:
    """``python -m autopower.cli.replay RUN.rrd ...`` (same error handling as ``autopower``)."""
    run_command(replay, argv, "autopower replay")


if __name__ == "__main__":
    main()
