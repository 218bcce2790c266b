"""Is it the team or the machine? A probe outside the team that notices when the whole machine stops.

A separate process sleeps 2 ms again and again and writes down every wake-up more than 10 ms
late (unix time at the wake-up, how late in ms). It carries no load of the team, so a stall it
sees is the machine's (the kernel, the hypervisor), not the team's. `attribute` then matches the
periods the agents logged as skipped (their `info` log: "source X is N period(s) late; skipped
them") with those stalls: on a machine measured here every missed period of the whole mission at
x55 fell within 0.1 s of a machine-wide stall (docs/performance.md).

Used by `bench_whole_mission.py --stall-probe`; run alone it probes for the seconds given:

    python bench/stall_probe.py 60
"""

from __future__ import annotations

import datetime
import os
import re
import subprocess
import sys
import time
from pathlib import Path

SLEEP_S = 0.002
LATE_MS = 10.0
# a skip is logged by the agent's loop once it runs again, so after the probe's wake-up, or just
# before it (both woke from the same stall; which process runs first is the scheduler's choice)
BEFORE_S, AFTER_S = 0.2, 0.5
SKIPPED = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) .*: source (\S+) is (\d+) period\(s\) late; skipped them")


def probe(seconds: float, parent: int | None = None) -> None:
    """Probe for ``seconds``, or until process ``parent`` is gone (the bench, however it ended)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end and (parent is None or os.getppid() == parent):
        start = time.perf_counter()
        time.sleep(SLEEP_S)
        late_ms = (time.perf_counter() - start - SLEEP_S) * 1e3
        if late_ms > LATE_MS:
            print(f"{time.time():.3f} {late_ms:.1f}", flush=True)


def start(out: Path, seconds: float) -> subprocess.Popen:
    """The probe in a process of its own, writing to ``out`` for at most ``seconds`` and no longer
    than this process lives."""
    with open(out, "w") as sink:
        return subprocess.Popen([sys.executable, __file__, str(seconds), str(os.getpid())], stdout=sink)


def stalls(out: Path) -> list[tuple[float, float]]:
    """(unix time of the wake-up, ms late) of each stall the probe wrote down; late wake-ups less
    than a second apart are one stall (its longest)."""
    late = []
    for line in out.read_text().splitlines():
        try:
            t, ms = line.split()
            late.append((float(t), float(ms)))
        except ValueError:
            continue
    found: list[tuple[float, float]] = []
    for t, ms in sorted(late):
        if found and t - found[-1][0] < 1.0:
            if ms > found[-1][1]:
                found[-1] = (t, ms)
        else:
            found.append((t, ms))
    return found


def skipped(log_dir: Path) -> list[tuple[float, str, int]]:
    """(unix time, 'robot chain', periods) of every skip the agents logged in ``log_dir``."""
    found = []
    for log in sorted(log_dir.glob("*.log")):
        for line in log.read_text(errors="replace").splitlines():
            m = SKIPPED.match(line)
            if m:
                # logging's asctime is local time, as datetime's naive timestamp() reads it
                t = datetime.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
                found.append((t, f"{log.stem} {m.group(2)}", int(m.group(3))))
    return found


def attribute(stall_list: list[tuple[float, float]], skips: list[tuple[float, str, int]]) -> dict:
    """How many skipped periods fell next to a machine stall, and the stalls that cost periods."""
    near = 0
    costly: dict[tuple[float, float], int] = {}  # stall -> periods skipped next to it
    for t, _, periods in skips:
        hits = [s for s in stall_list if s[0] - BEFORE_S <= t <= s[0] + AFTER_S]
        if hits:
            near += periods
            worst = max(hits, key=lambda s: s[1])
            costly[worst] = costly.get(worst, 0) + periods
    return {"stalls": len(stall_list), "longest_ms": max((ms for _, ms in stall_list), default=0.0),
            "skipped": sum(p for _, _, p in skips), "skipped_near_a_stall": near,
            # [ms late, periods] of each stall that cost periods, the longest first
            "costly_stalls": sorted(([ms, n] for (_, ms), n in costly.items()), reverse=True)}


def describe(result: dict) -> str:
    costs = ", ".join(f"{ms:.0f} ms -> {n}" for ms, n in result["costly_stalls"]) or "none"
    return (f"machine stalls seen by a probe outside the team (a 2 ms sleep woken > {LATE_MS:g} ms late): "
            f"{result['stalls']}, longest {result['longest_ms']:.0f} ms; periods the agents logged as skipped: "
            f"{result['skipped']}, of which {result['skipped_near_a_stall']} within "
            f"-{BEFORE_S:g}/+{AFTER_S:g} s of a stall (stall -> periods: {costs})")


if __name__ == "__main__":
    probe(float(sys.argv[1]) if len(sys.argv) > 1 else 60.0, int(sys.argv[2]) if len(sys.argv) > 2 else None)
