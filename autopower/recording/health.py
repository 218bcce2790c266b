"""Whether a live run's recording can be, and still is being, written.

The processes write their `<node>.rrd` through Rerun's file sink, whose write errors never reach
Python: a full or vanished disk would lose the recording without a word. The supervisor (`up`)
therefore checks the record directory itself: before the team starts (`check_record_dir`)
and every few seconds while it runs (`recording_problem`).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable

from autopower.errors import RecordingError

MIN_FREE_BYTES = 64 * 2**20  # below this a run's recording (MBs a minute) is about to fail


def _probe(directory: Path) -> None:
    """Create, write and remove a small file in `directory` (raises OSError if that fails)."""
    fd, name = tempfile.mkstemp(prefix=".autopower-probe-", dir=directory)
    try:
        os.write(fd, b"\0" * 4096)
        os.fsync(fd)
    finally:
        os.close(fd)
        os.unlink(name)


def check_record_dir(directory: str | Path) -> Path:
    """`directory`, created if needed, once it is known to take a recording; else one clear error."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        _probe(directory)
    except OSError as exc:
        raise RecordingError(f"--record-dir {directory}: cannot write there ({exc.strerror or exc}); "
                             "choose a directory you can write to") from None
    problem = _low_space(directory)
    if problem:
        raise RecordingError(f"--record-dir {directory}: {problem}; free some space or choose another disk")
    return directory


def _low_space(directory: Path) -> str | None:
    st = os.statvfs(directory)
    free = st.f_bavail * st.f_frsize
    if free < MIN_FREE_BYTES:
        return f"only {free / 2**20:.0f} MB free on its disk"
    return None


def recording_problem(directory: str | Path, nodes: Iterable[str]) -> str | None:
    """Why the run's recording is failing now (gone, unwritable, disk full, a file missing), or None."""
    directory = Path(directory)
    try:
        _probe(directory)
        problem = _low_space(directory)
    except OSError as exc:
        return f"cannot write to {directory} ({exc.strerror or exc})"
    if problem:
        return f"{directory}: {problem}"
    missing = [n for n in nodes if not (directory / f"{n}.rrd").is_file()]
    if missing:
        return f"{', '.join(f'{n}.rrd' for n in missing)} missing from {directory}"
    return None


__all__ = ["MIN_FREE_BYTES", "RecordingError", "check_record_dir", "recording_problem"]
