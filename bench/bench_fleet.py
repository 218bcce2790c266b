"""Live fleets beyond the paper's trio: `autopower up` on generated teams of N robots. Not a timed test.

    .venv/bin/python bench/bench_fleet.py [--robots 3,10,20,30] [--seconds 30] [--speed 1]

Each team is `autopower scenarios fleet N` (every robot the paper's camera robot: a Loc chain and a
4 Hz Blob chain each; fully connected 802.11a or GSM, the planner's choice), run by the installed
CLI as a user runs it, every process real and every link through its proxy, for ``--seconds`` of
wall time at ``--speed``. The first size is the baseline measured in the same run (3 robots: the
paper's team size). Printed per size: the time until the team is ready, the periods missed, the
CPU the whole team used (every process, per wall second and per robot), the outputs its sinks
took in with any gap or second copy, the largest gap between a robot's metered power and the
model's, and whether every process stopped by itself. A team that is not ready within the time
`up` allows is reported as such (its other figures are then missing).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results as bench_results

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_fleet(n: int, seconds: float, speed: float, folder: Path) -> dict:
    env = {**os.environ, "AUTOPOWER_STATE_DIR": str(folder / f"state-{n}"), "RERUN_ANALYTICS": "0"}
    scenario = folder / f"fleet-{n}.toml"
    subprocess.run([AUTOPOWER, "scenarios", "fleet", str(n), "--out", str(scenario)], env=env, check=True,
                   capture_output=True, timeout=120)
    cpu0, started = children_cpu_s(), time.monotonic()
    proc = subprocess.run([AUTOPOWER, "up", str(scenario), "--speed", f"{speed:g}", "--duration", f"{seconds:g}",
                           "--json", "--log-dir", str(folder / f"logs-{n}")], env=env, capture_output=True, text=True,
                          timeout=seconds + 600)
    wall, cpu = time.monotonic() - started, children_cpu_s() - cpu0
    try:
        summary = json.loads(proc.stdout)
    except json.JSONDecodeError:
        summary = {"error": (proc.stderr or proc.stdout)[-300:]}
    out = {"robots": n, "exit": proc.returncode, "wall_s": wall, "cpu_s": cpu, "ready": bool(summary.get("ready"))}
    if not out["ready"]:
        out["error"] = str(summary.get("error", ""))[:200]
        return out
    sinks = {**summary["basestation"]["sinks"],
             **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    run_wall = wall - summary["ready_after_s"]
    out.update(ready_after_s=summary["ready_after_s"], missed_pct=summary["missed_periods_pct"],
               outputs=sum(s["received"] for s in sinks.values()),
               gaps=sum(s["max_seq"] + 1 - s["contiguous"] for s in sinks.values()),
               duplicates=sum(s["duplicates_total"] for s in sinks.values()),
               power_error_pct=100 * max(abs(r["power_error"]) for r in summary["robots"].values()),
               clean=all(code == 0 for code in summary["exit_codes"].values()),
               cores=cpu / wall, run_wall_s=run_wall)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default="3,10,20,30")
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--speed", type=float, default=1.0)
    bench_results.add_json_out(parser)
    args = parser.parse_args()
    sizes = [int(x) for x in args.robots.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        runs = [run_fleet(n, args.seconds, args.speed, Path(tmp)) for n in sizes]
    base = runs[0]
    print(f"{'robots':>6} {'ready s':>8} {'missed %':>9} {'cores':>6} {'CPU s/robot':>12} {'outputs':>8} "
          f"{'gaps':>5} {'dups':>5} {'|power err| %':>14} {'clean':>6}")
    for r in runs:
        if not r["ready"]:
            print(f"{r['robots']:>6} not ready ({r['error'][:90]})")
            continue
        print(f"{r['robots']:>6} {r['ready_after_s']:>8.1f} {r['missed_pct']:>9.2f} {r['cores']:>6.2f} "
              f"{r['cpu_s'] / r['robots']:>12.2f} {r['outputs']:>8} {r['gaps']:>5} {r['duplicates']:>5} "
              f"{r['power_error_pct']:>14.2f} {str(r['clean']):>6}")
    note = f"the {base['robots']}-robot fleet, run the same way in the same run"
    figures = []
    for r in runs[1:]:
        g = f"{r['robots']} robots"
        if not r["ready"]:
            figures.append(bench_results.figure("ready (1: yes, 0: no)", 0, "", f"{base['robots']} robots",
                                                1 if base["ready"] else 0, group=g, note=note,
                                                detail=f"not ready within the time `up` allows: {r['error'][:120]}"))
            continue
        if not base["ready"]:
            raise SystemExit(f"the baseline ({base['robots']} robots) did not become ready: {base.get('error')}")
        figures += [
            bench_results.figure("time until ready", r["ready_after_s"], "s", f"{base['robots']} robots",
                                 base["ready_after_s"], group=g, note=note),
            bench_results.figure("periods missed", r["missed_pct"], "%", f"{base['robots']} robots",
                                 base["missed_pct"], group=g, note=note),
            bench_results.figure("CPU of the whole team per robot", r["cpu_s"] / r["robots"], "CPU s",
                                 f"{base['robots']} robots", base["cpu_s"] / base["robots"], group=g, note=note,
                                 detail=f"{r['cores']:.2f} cores in all over {r['wall_s']:.0f} s of wall time"),
            bench_results.figure("outputs missing or repeated at the sinks", r["gaps"] + r["duplicates"], "outputs",
                                 "outputs the sinks took in", r["outputs"], group=g,
                                 note="every sink's ledger at the end (gaps below its highest seq, second copies)"),
            bench_results.figure("largest |metered - model| power of a robot", r["power_error_pct"], "%",
                                 f"{base['robots']} robots", base["power_error_pct"], group=g, note=note),
            bench_results.figure("processes that did not stop by themselves", 0 if r["clean"] else 1, "teams",
                                 f"{base['robots']} robots", 0 if base["clean"] else 1, group=g, note=note),
        ]
    bench_results.write_result("fleet", {"robots": sizes, "seconds": args.seconds, "speed": args.speed}, figures,
                               args.json_out, what=__doc__.splitlines()[0], extra={"runs": runs})


if __name__ == "__main__":
    main()
