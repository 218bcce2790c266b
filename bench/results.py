"""What every bench shares: the machine's facts, and one JSON file of figures per run.

A bench measures its figures and, asked for it (``--json-out PATH``, or the environment's
``AUTOPOWER_BENCH_JSON``), writes them with `write_result`. Each figure carries the baseline it is
measured against in the same run and the ratio, so a reader on any machine can judge it. The
file also says the machine, the date (UTC) and the parameters of that run; `bench/report.py`
renders the documentation's tables from these files.

A figure (one row of a table)::

    {"name": "decode, camera frame 230 kB", "value": 61.2, "unit": "us",
     "baseline": "bare msgpack", "baseline_value": 40.1, "ratio": 1.526,
     "baseline_note": "msgpack.unpackb of the same bytes, no field checked",
     "group": "strict codec, CPU per message", "detail": ""}

``ratio`` is value / baseline_value unless the bench gives its own; ``group`` puts figures in one
table (in the order they first appear); ``detail`` is an optional column (a placement, say);
``also`` optionally holds more baselines of the same figure (each with baseline, baseline_value,
ratio and baseline_note), shown as more columns.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

SCHEMA = 1
ENV = "AUTOPOWER_BENCH_JSON"
STARTED = time.time()  # when the bench imported this module: its run's duration is counted from here
ROOT = Path(__file__).resolve().parents[1]


def load() -> str:
    """The load average (1, 5, 15 minutes) as /proc shows it."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def proc_status_kb(pid: int, field: str) -> int | None:
    """A memory figure of a live process in KiB, as /proc/<pid>/status shows it (``VmRSS``, the
    peak ``VmHWM``, ...); None if the kernel does not list it; OSError once the process is gone."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    return None


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def os_name() -> str:
    try:
        for line in Path("/etc/os-release").read_text().splitlines():
            if line.startswith("PRETTY_NAME="):
                return line.split("=", 1)[1].strip().strip('"')
    except OSError:
        pass
    return platform.system()


def machine() -> dict:
    """The facts that say which machine measured a figure (the same for every bench)."""
    return {"cpu": cpu_model(), "cores": os.cpu_count() or 1, "python": platform.python_version(),
            "os": os_name(), "kernel": f"{platform.system()} {platform.release()}", "arch": platform.machine()}


def commit() -> str | None:
    """The code measured: the checkout's commit, '+' when it has changes not committed."""
    try:
        sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short=12", "HEAD"], capture_output=True,
                             text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (sha + ("+" if dirty else "")) or None


def ratio(value, baseline_value) -> float | None:
    try:
        r = float(value) / float(baseline_value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return r if math.isfinite(r) else None


def figure(name: str, value, unit: str, baseline: str, baseline_value, *, note: str = "", group: str = "",
           detail: str = "", ratio_: float | None = None, baseline_unit: str | None = None,
           also: list[tuple[str, object, str]] = ()) -> dict:
    """One row: ``value`` against ``baseline_value`` (measured in the same run; ``note`` says what it is),
    and against each (baseline, baseline_value, note) of ``also``."""
    out = {"name": name, "value": value, "unit": unit, "baseline": baseline, "baseline_value": baseline_value,
           "ratio": ratio_ if ratio_ is not None else ratio(value, baseline_value), "baseline_note": note}
    if baseline_unit is not None and baseline_unit != unit:
        out["baseline_unit"] = baseline_unit
    if group:
        out["group"] = group
    if detail:
        out["detail"] = detail
    if also:
        out["also"] = [{"baseline": b, "baseline_value": v, "ratio": ratio(value, v), "baseline_note": n}
                       for b, v, n in also]
    return out


def add_json_out(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json-out", default=os.environ.get(ENV) or None, metavar="PATH",
                        help="also write the figures, with their baselines, the machine and the date, to PATH "
                             f"(bench/report.py renders the docs' tables from it; default ${ENV})")


def pop_json_out(argv: list[str] | None = None) -> str | None:
    """``--json-out PATH`` taken out of ``argv`` (sys.argv) for a bench that reads its arguments by hand."""
    argv = sys.argv if argv is None else argv
    for i, arg in enumerate(argv):
        if arg == "--json-out" and i + 1 < len(argv):
            path = argv[i + 1]
            del argv[i:i + 2]
            return path
        if arg.startswith("--json-out="):
            del argv[i]
            return arg.split("=", 1)[1]
    return os.environ.get(ENV) or None


def command() -> list[str]:
    """How this bench was started (its path from the repository's root; --json-out left out)."""
    argv = list(sys.argv) or [""]
    try:
        argv[0] = Path(argv[0]).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        pass
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--json-out":
            skip = True
        elif not arg.startswith("--json-out="):
            out.append(arg)
    return out


def _clean(x):
    """JSON has no NaN or infinity: they become null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    return x


def write_result(bench: str, params: dict, figures: list[dict], path: str | os.PathLike | None, *, what: str,
                 groups: dict[str, dict] | None = None, extra: dict | None = None) -> dict:
    """Write one run's figures to ``path`` (nothing when ``path`` is None); returns the document.

    ``groups`` may give a table's headers (``value``, ``baseline``, ``baseline_value``, ``detail``) and
    a line above it (``what``), by group name. ``extra`` is kept in the file, not rendered.
    """
    doc = {"schema": SCHEMA, "bench": bench, "what": what.strip(),
           "date_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
           "duration_s": round(time.time() - STARTED, 1), "machine": machine(), "commit": commit(),
           "command": command(),
           "params": params, "load_average_end": load(), "groups": groups or {}, "figures": figures}
    if extra:
        doc["extra"] = extra
    doc = _clean(doc)
    if path is None:
        return doc
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1, ensure_ascii=False) + "\n")
    tmp.replace(path)  # a reader never sees half a file
    sys.stdout.flush()
    print(f"(figures written to {path})", file=sys.stderr)
    return doc
