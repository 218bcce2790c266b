"""Scenario loading at fleet scale: `autopower check` of N robots, time and peak memory.

    .venv/bin/python bench/bench_loading.py [ROBOTS ...]   (default: 250 2000)

Not a timed test. Each fleet (N robots, one localisation chain per robot, fully connected with
relay analysis, as in paper-fig7: what `autopower scenarios fleet N --cameras 0` writes) is written
as a TOML file and checked by the installed command in a subprocess, so the figures are what a
user waits for: wall time and the process's peak RSS. The smallest fleet is the baseline: the ratio of time per robot against
it says whether loading grows linearly (about 1x) or worse (the N^2/2 implied robot-robot
links once made 2,000 robots take 78 s and 1.8 GB).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results as bench_results

from autopower.simulation.synthetic import paper_fleet

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def fleet_toml(n: int) -> str:
    """The fleet `autopower scenarios fleet N --cameras 0` writes: paper-fig7's platforms, radios and
    network on N robots, one Loc chain each (autopower.simulation.synthetic.paper_fleet)."""
    return paper_fleet(n, cameras=0)[0]


def check(path: Path) -> tuple[float, float]:
    """(wall seconds, peak RSS in MB) of `autopower check PATH`."""
    started = time.monotonic()
    proc = subprocess.Popen([AUTOPOWER, "check", str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "RERUN_ANALYTICS": "0"})
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.monotonic() - started
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"check of {path} failed: {proc.stderr.read().decode()[-500:]}")
    return wall, usage.ru_maxrss / 1024  # Linux reports KiB


def main(sizes: list[int], json_out: str | None = None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        results = []
        for n in sizes:
            path = Path(tmp) / f"fleet-{n}.toml"
            path.write_text(fleet_toml(n))
            wall, rss = check(path)
            results.append((n, wall, rss, path.stat().st_size))
        base_n, base_wall, base_rss, _ = results[0]
        print(f"{'robots':>7} {'file':>9} {'check s':>8} {'peak MB':>8} {'s/robot vs ' + str(base_n):>16}")
        for n, wall, rss, size in results:
            ratio = (wall / n) / (base_wall / base_n)
            print(f"{n:>7} {size / 1024:>7.0f}KB {wall:>8.2f} {rss:>8.0f} {ratio:>15.2f}x")
        print("(time includes the CLI's start-up, which the smallest fleet is mostly made of; "
              "a ratio at or below 1x means loading grows no faster than linearly)")
    note = f"the smallest fleet ({base_n} robots), checked the same way in the same run"
    figures = []
    for n, wall, rss, _size in results[1:]:
        figures += [
            bench_results.figure(f"{n} robots: check time per robot", wall / n * 1e3, "ms", f"{base_n} robots",
                           base_wall / base_n * 1e3, note=note),
            bench_results.figure(f"{n} robots: check time", wall, "s", f"{base_n} robots", base_wall, note=note),
            bench_results.figure(f"{n} robots: peak memory", rss, "MB", f"{base_n} robots", base_rss, note=note),
        ]
    bench_results.write_result("loading", {"robots": sizes}, figures, json_out, what=__doc__.splitlines()[0])


if __name__ == "__main__":
    out = bench_results.pop_json_out()
    main([int(a) for a in sys.argv[1:]] or [250, 2000], out)
