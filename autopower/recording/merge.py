"""Merging a run's per-process recordings into one `run.rrd` with the `rerun` tool.

``rerun rrd optimize`` merges and compacts in one pass: each process flushes a small chunk per
entity every second, which a viewer would otherwise load as thousands of tiny chunks. The merged
file also gets the run's view (`autopower.recording.blueprint.design` of what the processes
logged), written as one more input; the per-process files carry none, so there is exactly one.
"""

from __future__ import annotations

import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Iterable, Sequence

from autopower.errors import AutoPowerError

log = logging.getLogger(__name__)
from autopower.recording.recorder import MERGED_NAME


def rerun_binary() -> str:
    """The ``rerun`` executable of this environment.

    Prefers the real binary shipped in ``rerun_cli`` over the venv's ``rerun`` (a Python wrapper
    next to the interpreter, which survives SIGTERM without stopping its child): a process we
    start must be one we can stop by its own pid. Then the wrapper, then PATH.
    """
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun")
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    except ImportError:
        pass
    here = Path(sys.executable).parent / "rerun"
    if here.is_file():
        return str(here)
    found = shutil.which("rerun")
    if found is None:
        raise AutoPowerError("the 'rerun' command is not installed next to Python or on PATH; "
                             "install rerun-sdk in this environment")
    return found


def rerun_env() -> dict[str, str]:
    return {**os.environ, "RERUN_ANALYTICS": "0"}


def merge_recordings(files: Iterable[str | Path], out: str | Path, *, timeout_s: float = 60.0,
                     blueprint: bool = True) -> Path:
    """Merge per-process files of one run into `out` with ``rerun rrd optimize`` (merged and compacted),
    with the run's blueprint unless `blueprint` is False.

    Missing or empty files are skipped (a process that died before writing anything); raises
    `RecordingError` if nothing is left or the merge fails.
    """
    from autopower.errors import RecordingError

    out = Path(out)
    inputs = [str(f) for f in files if Path(f).is_file() and Path(f).stat().st_size > 0
              and Path(f).resolve() != out.resolve()]
    if not inputs:
        raise RecordingError(f"{out}: no per-process recording to merge; check that the processes were "
                             "started with a recording directory")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    view = out.with_name(out.name + ".rbl.part")
    if blueprint:
        _write_blueprint(inputs, view)
        inputs.append(str(view))
    cmd = [rerun_binary(), "rrd", "optimize", "--continue-on-error", "-o", str(tmp), *inputs]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=rerun_env(),
                              stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"{out}: 'rerun rrd optimize' (merging) took more than {timeout_s:.0f} s") from None
    finally:
        view.unlink(missing_ok=True)
    if done.returncode != 0 or not tmp.is_file():
        tmp.unlink(missing_ok=True)
        raise RecordingError(f"{out}: 'rerun rrd optimize' (merging) failed ({done.returncode}): "
                             f"{(done.stderr or done.stdout).strip()[-400:]}")
    os.replace(tmp, out)
    return out


def _write_blueprint(inputs: Sequence[str], path: Path) -> None:
    """The run's view, from the union of what the per-process files hold; a file that cannot be read
    (a process killed mid-write) adds nothing to it rather than failing the merge."""
    from autopower.recording.blueprint import design
    from autopower.recording.telemetry import APPLICATION_ID, Layout, read_recording

    layout = Layout()
    for name in inputs:
        try:
            layout.merge(read_recording(name).layout)
        except Exception as exc:  # noqa: BLE001 - a foreign or truncated file still merges as data
            log.warning("merge: %s adds nothing to the run's view (%s)", name, exc)
    design(layout).save(APPLICATION_ID, str(path))


def merge_run(run_dir: str | Path) -> Path:
    """Merge every ``<node>.rrd`` of `run_dir` into ``<run_dir>/run.rrd``."""
    run_dir = Path(run_dir)
    files: Sequence[Path] = sorted(p for p in run_dir.glob("*.rrd") if p.name != MERGED_NAME)
    return merge_recordings(files, run_dir / MERGED_NAME)


