"""`autopower recording merge DIR`: build a run's `run.rrd` from its per-process recordings.

`up --record-dir DIR` merges them itself when it stops; after a crash, a SIGKILL or a double
Ctrl-C it cannot, and the per-process files (`laptop.rrd`, `r1.rrd`, ...) are all there is.
"""

from __future__ import annotations

from pathlib import Path

import click

from autopower.errors import RecordingError
from autopower.recording.recorder import MERGED_NAME


@click.group("recording")
def recording() -> None:
    """Work with a run's Rerun recordings."""


@recording.command("merge")
@click.argument("run_dir", metavar="DIR", type=click.Path(file_okay=False))
def merge(run_dir: str) -> None:
    """Merge DIR's per-process recordings into DIR/run.rrd (after a run that was cut short)."""
    from autopower.recording.merge import merge_run

    folder = Path(run_dir)
    if not folder.is_dir():
        raise RecordingError(f"{folder}: no such directory; give the --record-dir of the run")
    parts = sorted(p.name for p in folder.glob("*.rrd") if p.name != MERGED_NAME)
    out = merge_run(folder)
    click.echo(f"{out}: merged {len(parts)} recordings ({', '.join(parts)}); autopower replay {out}")


COMMANDS = (recording,)
