"""CPU of processes with nothing to do: a base station waiting for robots, a whole team at rest.

    .venv/bin/python bench/bench_idle.py [--baseline PATH/TO/autopower] [--seconds S]

Not a timed test. CPU is read from /proc (user + system ticks) over S wall seconds and shown as
a percentage of one core:
- a lone base station waiting for its robots (no agent ever comes);
- a whole team under `up` (base station, three agents, link proxies and `up` itself) with
  every chain disabled, i.e. at rest; beside it, the same team running its chains, measured
  in the same run, as the baseline the rest is compared with.
With --baseline, the waiting base station of another build is measured too (e.g. one whose
wake-up time was 0 until the first plan, which spun a core).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

AUTOPOWER = str(Path(sys.executable).parent / "autopower")
TICKS = os.sysconf("SC_CLK_TCK")


def cpu_ticks(pids) -> int:
    total = 0
    for pid in pids:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])  # utime, stime
        except (OSError, IndexError):
            pass
    return total


def tree(pid: int) -> list[int]:
    """`pid` and every descendant (children of children included)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            kids = []
        todo.extend(int(k) for k in kids)
    return out


def percent_of_core(pids_fn, seconds: float) -> float:
    before, t0 = cpu_ticks(pids_fn()), time.monotonic()
    time.sleep(seconds)
    after, t1 = cpu_ticks(pids_fn()), time.monotonic()
    return 100.0 * (after - before) / TICKS / (t1 - t0)


def waiting_basestation(command: str, seconds: float) -> float:
    proc = subprocess.Popen([command, "basestation", "--team", f"idle{os.getpid()}", "--listen", "tcp/127.0.0.1:0",
                             "--log-level", "error"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ, "RERUN_ANALYTICS": "0"})
    try:
        time.sleep(3.0)  # past start-up
        return percent_of_core(lambda: [proc.pid], seconds)
    finally:
        proc.terminate()
        proc.wait(15)


def team_at_rest(seconds: float) -> tuple[float, float]:
    """(% of a core running its chains, % with every chain disabled) for a whole team under `up`."""
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "AUTOPOWER_STATE_DIR": str(Path(tmp) / "state"), "RERUN_ANALYTICS": "0"}
        team = f"rest{os.getpid()}"
        up = subprocess.Popen([AUTOPOWER, "up", "--team", team, "--json", "--log-dir", str(Path(tmp) / "logs")],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        try:
            def status() -> dict:
                out = subprocess.run([AUTOPOWER, "status", "--team", team, "--json", "--timeout", "3"], env=env,
                                     capture_output=True, text=True, timeout=30)
                return json.loads(out.stdout) if out.returncode == 0 else {}

            deadline = time.monotonic() + 90
            while not status().get("ready"):
                if time.monotonic() > deadline or up.poll() is not None:
                    raise SystemExit("the team did not get ready")
                time.sleep(1.0)
            time.sleep(2.0)
            running = percent_of_core(lambda: tree(up.pid), seconds)
            for chain in status().get("running") or []:
                subprocess.run([AUTOPOWER, "chain", "disable", chain, "--team", team], env=env,
                               capture_output=True, timeout=30)
            time.sleep(3.0)  # the last frames drain
            rest = percent_of_core(lambda: tree(up.pid), seconds)
            return running, rest
        finally:
            up.send_signal(signal.SIGINT)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                up.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default=None)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(f"CPU over {args.seconds:g} s wall, % of one core")
    print(f"  base station waiting for robots (this build): {waiting_basestation(AUTOPOWER, args.seconds):6.2f} %")
    if args.baseline:
        print(f"  base station waiting for robots (baseline):   {waiting_basestation(args.baseline, args.seconds):6.2f} %")
    running, rest = team_at_rest(args.seconds)
    print(f"  whole team (up + base station + 3 agents + link proxies), chains running: {running:6.2f} %")
    print(f"  the same team at rest (every chain disabled):                              {rest:6.2f} %"
          f"  ({rest / running:.2f}x running)")


if __name__ == "__main__":
    main()
