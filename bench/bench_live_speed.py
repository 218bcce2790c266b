"""How fast a live team keeps up: missed periods, CPU per process and latency at each speed-up.

    .venv/bin/python bench/bench_live_speed.py [--seconds 20] [--speeds 10,20,50,100]
                                               [--stage-workers off,on] [--baseline-tree DIR] [--json]

The mission is the paper's (paper-fig7, what `autopower up` and `demo` run by default): a real
localhost team (base station + three agents, mutual TLS, real components) at each speed-up.

The limit is what this machine can do at best: its cores divided by the CPU seconds the mission's
components themselves need per virtual second (each chain's runs per virtual second times its
component's median run time, measured here as `autopower profile` measures it). A team that
kept up at the limit would spend all its CPU in the components and none in the runtime.

For each speed (10x, 20x, 50x, 100x and the limit) it prints, over ``--seconds`` of wall time
counted from the moment the team is ready: source periods missed (%), frames resent by custody,
chain data dropped by a full event queue and resent inputs dropped as redundant, the CPU each process used
(utime + stime from /proc/PID/stat over that window, in % of one core), and each sink's
end-to-end latency p50. With ``--baseline-tree DIR`` (a checkout of the code before, e.g.
``git archive main | tar -x -C DIR``) the same runs are made first with the team's processes
running that code (PYTHONPATH=DIR), so the ratio is measured in the same bench run.
``--stage-workers off,on`` (the default) runs every speed with the processes' ``--stage-workers``
off and then on (each hosted stage's component in a worker process: the base station's five
stages in parallel), so the two are compared in the same bench run; a node's CPU includes its
worker processes, and the base station's loop process alone is printed beside it ("loop %").
Not a timed test: the machine's load average is printed beside every run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import results

from autopower.chains import profile_components
from autopower.chains.profile import live_limit
from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.launch.summary import chain_latencies
from autopower.runtime.memory import keep_large_buffers

SCENARIO = "paper-fig7"
TICKS = os.sysconf("SC_CLK_TCK")


def component_cpu_per_virtual_s(scenario, runs: int = 40) -> tuple[float, dict[str, float]]:
    """CPU seconds the mission's components need per virtual second (all of them on this machine)."""
    kinds = sorted({stage.component for chain in scenario.chains for stage in chain.stages})
    keep_large_buffers()  # as `autopower profile` and the team's processes run them
    profile = profile_components(runs, types=kinds)
    need, _ = live_limit(scenario, profile, 1)
    return need, {k: p["latency_median_s"] for k, p in profile.items()}


def cpu_s(pid: int) -> float | None:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime (fields 14 and 15)


def tree_cpu_s(pid: int) -> float | None:
    """CPU seconds of ``pid`` and every live process below it (a node's stage workers)."""
    own = cpu_s(pid)
    if own is None:
        return None
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            parents.setdefault(ppid, []).append(int(entry))
    total, todo = own, list(parents.get(pid, []))
    while todo:
        child = todo.pop()
        total += cpu_s(child) or 0.0
        todo += parents.get(child, [])
    return total


def missed(snap: dict) -> tuple[int, int]:
    produced = missed_ = 0
    for info in (snap.get("robots") or {}).values():
        for s in ((info.get("status") or {}).get("sources") or {}).values():
            produced += s.get("produced_total", 0)
            missed_ += s.get("missed", 0)
    return produced, missed_


def resends(snap: dict) -> tuple[int, int, int]:
    """Frames resent by every node (custody), chain data the nodes' event queues dropped when full,
    and resent inputs their stages dropped as redundant (they had arrived, only late), so far."""
    statuses = [(info.get("status") or {}) for info in (snap.get("robots") or {}).values()]
    statuses.append(snap.get("basestation") or {})
    resent = sum((s.get("counters") or {}).get("resent-frames", 0) for s in statuses)
    shed = sum((s.get("errors") or {}).get("queue-full", 0) for s in statuses)
    redundant = sum((s.get("counters") or {}).get("redundant-input", 0) for s in statuses)
    return resent, shed, redundant


def stage_runs(snap: dict, node: str) -> int:
    """Inputs the stages hosted on ``node`` have run so far (from its status in the snapshot)."""
    status = snap.get("basestation") if node == "basestation" else ((snap.get("robots") or {}).get(node) or {}).get("status")
    return sum(((status or {}).get("runs") or {}).values())


def run_once(speed: float, seconds: float, tree: str | None, workers: str = "auto") -> dict:
    scenario = build_scenario(SCENARIO)
    saved, cwd = os.environ.get("PYTHONPATH"), os.getcwd()
    if tree:
        os.environ["PYTHONPATH"] = tree  # the children run that code; this process keeps its own
        # and from there: `python -m` puts the working directory first on sys.path, so children
        # started in a checkout (the repository's root) imported its code, not the tree's
        os.chdir(tree)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            spec = TeamSpec(scenario=SCENARIO, speed=speed, log_dir=Path(tmp), log_level="warning",
                            **({"stage_workers": workers} if not tree else {}))  # the code before has no option
            with LocalTeam(spec, scenario) as team:
                team.wait_ready(120)
                pids = {name: child.proc.pid for name, child in team.children.items()}
                snap0 = team.snapshot()
                cpu0 = {n: tree_cpu_s(p) for n, p in pids.items()}
                loop0 = cpu_s(pids[scenario.basestation])
                wall0 = time.monotonic()
                load0 = os.getloadavg()[0]
                time.sleep(seconds)
                snap1 = team.snapshot()
                cpu1 = {n: tree_cpu_s(p) for n, p in pids.items()}
                loop1 = cpu_s(pids[scenario.basestation])
                wall = time.monotonic() - wall0
                load1 = os.getloadavg()[0]
    finally:
        if tree:
            os.chdir(cwd)
            if saved is None:
                os.environ.pop("PYTHONPATH", None)
            else:
                os.environ["PYTHONPATH"] = saved
    (p0, m0), (p1, m1) = missed(snap0), missed(snap1)
    resent, shed, redundant = (b - a for a, b in zip(resends(snap0), resends(snap1), strict=True))
    produced, miss = p1 - p0, m1 - m0
    cpu = {n: (cpu1[n] - cpu0[n]) / wall * 100 for n in pids if cpu0[n] is not None and cpu1[n] is not None}
    latencies = {c: v["p50_ms"] for c, v in chain_latencies(snap1).items()}
    # the base station's CPU per input its stages ran (all of them, in the paper's optimum): what
    # one camera or laser frame costs it, components included, whatever the machine's load
    base_runs = stage_runs(snap1, "basestation") - stage_runs(snap0, "basestation")
    base_cpu_s = cpu.get(scenario.basestation, 0.0) / 100 * wall
    virtual = (snap1.get("t_virtual") or 0) - (snap0.get("t_virtual") or 0)
    return {"speed": speed, "wall_s": wall, "virtual_s": virtual, "produced": produced, "missed": miss,
            "missed_pct": 100.0 * miss / (produced + miss) if produced + miss else 0.0,
            "resent": resent, "queue_full": shed, "redundant": redundant,
            "cpu_pct": cpu, "latency_p50_ms": latencies, "load": (load0, load1), "base_runs": base_runs,
            "base_ms_per_run": base_cpu_s / base_runs * 1e3 if base_runs else None,
            "base_loop_pct": (loop1 - loop0) / wall * 100 if loop0 is not None and loop1 is not None else None}


def show(label: str, r: dict, nodes: list[str]) -> None:
    lat = r["latency_p50_ms"]
    blob = max((v for c, v in lat.items() if c.startswith("Blob") and v is not None), default=float("nan"))
    loc = max((v for c, v in lat.items() if c.startswith("Loc") and v is not None), default=float("nan"))
    cpu = " ".join(f"{r['cpu_pct'].get(n, float('nan')):>7.1f}" for n in nodes)
    total = sum(r["cpu_pct"].values())
    per_virtual_ms = total / 100 * r["wall_s"] / r["virtual_s"] * 1e3 if r["virtual_s"] else float("nan")
    loop = r.get("base_loop_pct")
    per_run = r.get("base_ms_per_run")
    print(f"{label:9} {r['speed']:>7.1f} {r['missed_pct']:>8.2f} {r['missed']:>6}/{r['produced'] + r['missed']:<6} "
          f"{r.get('resent', 0):>6} {r.get('queue_full', 0):>6} {r.get('redundant', 0):>6} "
          f"{cpu} {loop if loop is not None else float('nan'):>7.1f} {total:>7.1f} {per_virtual_ms:>8.1f} "
          f"{per_run if per_run is not None else float('nan'):>8.2f} "
          f"{blob:>10.1f} {loc:>10.1f}  {r['load'][0]:.2f}/{r['load'][1]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="wall seconds measured per speed (after ready)")
    ap.add_argument("--speeds", default="10,20,50,100", help="speed-ups to run besides the limit")
    ap.add_argument("--no-limit", action="store_true", help="do not run at the computed limit")
    ap.add_argument("--baseline-tree", default=None, metavar="DIR",
                    help="also run every speed with the team's processes on the code in DIR (before)")
    ap.add_argument("--stage-workers", default="off,on", metavar="MODES",
                    help="the processes' --stage-workers modes to run at every speed, in order (off, on, auto)")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON at the end")
    results.add_json_out(ap)
    args = ap.parse_args()

    scenario = build_scenario(SCENARIO)
    cores = os.cpu_count() or 1
    need, medians = component_cpu_per_virtual_s(scenario)
    limit = cores / need
    print(f"== live speed on {SCENARIO} ({cores} cores, load average {os.getloadavg()[0]:.2f}) ==")
    print("components (median ms per run here): " + ", ".join(f"{k} {v * 1e3:.2f}" for k, v in medians.items()))
    print(f"components need {need * 1e3:.2f} ms of CPU per virtual second -> limit = {cores} cores / that = "
          f"x{limit:.0f}; 60 % of it = x{0.6 * limit:.0f}")
    speeds = [float(s) for s in args.speeds.split(",") if s]
    if not args.no_limit:
        speeds.append(round(limit))
    nodes = [scenario.basestation] + [r.name for r in scenario.robots]
    header = (f"{'code':9} {'speed':>7} {'missed%':>8} {'missed/periods':>13} {'resent':>6} {'q-full':>6} {'redund':>6} "
              + " ".join(f"{n + ' %':>7}" for n in nodes)
              + f" {'loop %':>7} {'all %':>7} {'ms/virt':>8} {'base ms/in':>8} {'Blob p50ms':>10} {'Loc p50ms':>10}"
              "  load 1-min start/end")
    print(f"\nCPU in % of one core over {args.seconds:g} s of wall time after ready (a node's worker processes "
          "included; loop % = the base station's own process); ms/virt = the whole team's CPU "
          "ms per virtual second (compare with the components' need above); base ms/in = the base station's "
          "CPU ms per input its stages ran (components included); resent = frames the nodes resent "
          "(custody), q-full = chain data their event queues dropped when full, redund = resent inputs "
          "dropped on arrival as redundant (they had come, only late); latency p50 = a sink's "
          "capture-to-receipt wall ms (worst chain of each kind)")
    print(header)
    modes = [m for m in args.stage_workers.split(",") if m]
    runs = [("before", args.baseline_tree, "auto")] if args.baseline_tree else []
    runs += [(f"workers {m}", None, m) for m in modes]
    measured: dict[str, list[dict]] = {label: [] for label, _, _ in runs}
    for speed in speeds:
        for label, tree, mode in runs:
            try:
                r = run_once(speed, args.seconds, tree, mode)
            except Exception as exc:  # one speed that cannot start must not lose the others' figures
                print(f"{label:9} {speed:>7.1f} failed: {exc}".splitlines()[0])
                continue
            measured[label].append(r)
            show(label, r, nodes)
            sys.stdout.flush()
    if args.baseline_tree:  # the base station's CPU per input, this code against the code before, same run
        print("\nbase station CPU per input, after / before (same speed, alternating runs):")
        for label in [lbl for lbl in measured if lbl != "before"]:
            before_at = {r["speed"]: r for r in measured["before"]}
            for after in measured[label]:
                b, a = (before_at.get(after["speed"]) or {}).get("base_ms_per_run"), after.get("base_ms_per_run")
                if b and a:
                    print(f"  x{after['speed']:g} {label}: {a:.2f} / {b:.2f} ms = {a / b:.2f}")
    write(args, scenario, need, limit, measured)
    if args.json:
        print(json.dumps({"cores": cores, "component_cpu_s_per_virtual_s": need, "limit": limit,
                          "medians_s": medians, **measured}, indent=1))


def write(args, scenario, need: float, limit: float, measured: dict[str, list[dict]]) -> None:
    """Per speed and mode: periods missed against periods due, the team's CPU per virtual second against
    the components' own need, each kind of chain's latency against its period, and the base station's
    CPU per input with stage workers on against off (or against the code before)."""
    periods = {kind: min(c.period_s for c in scenario.chains if c.name.startswith(kind)) for kind in ("Blob", "Loc")}
    need_note = ("CPU ms the mission's components need per virtual second, measured here as `autopower profile` "
                 f"does (the limit, {os.cpu_count()} cores / that, is x{limit:.0f})")
    figures = []
    for label, runs in measured.items():
        for r in runs:
            g = f"x{r['speed']:g}, {label}"
            due = r["produced"] + r["missed"]
            total = sum(r["cpu_pct"].values())
            per_virtual = total / 100 * r["wall_s"] / r["virtual_s"] * 1e3 if r["virtual_s"] else None
            figures += [
                results.figure("source periods missed", r["missed"], "periods", "periods due", due, group=g,
                               note=f"every source period over {args.seconds:g} s of wall time"),
                results.figure("the team's CPU per virtual second", per_virtual, "ms", "the components' need",
                               need * 1e3, group=g, note=need_note),
            ]
            for kind, period in periods.items():
                lat = [v for c, v in r["latency_p50_ms"].items() if c.startswith(kind) and v is not None]
                if lat:
                    figures.append(results.figure(f"{kind} latency p50, worst chain", max(lat), "ms",
                                                  f"{kind} period", period / r["speed"] * 1e3, group=g,
                                                  note="the chain's period in wall time at that speed"))
    pairs = [("workers on", "workers off")] + [(label, "before") for label in measured if label != "before"]
    for label, base_label in pairs:
        base_at = {r["speed"]: r for r in measured.get(base_label, [])}
        for r in measured.get(label, []):
            b = base_at.get(r["speed"], {}).get("base_ms_per_run")
            if b and r.get("base_ms_per_run"):
                figures.append(results.figure(
                    f"x{r['speed']:g}, {label}: base station CPU per input", r["base_ms_per_run"], "ms", base_label,
                    b, group=f"base station CPU per input, against {base_label}",
                    note=f"the same on --baseline-tree {args.baseline_tree}" if base_label == "before"
                    else f"the same speed with stage {base_label}"))
    results.write_result("live_speed", {"seconds": args.seconds, "speeds": args.speeds, "no_limit": args.no_limit,
                                        "stage_workers": args.stage_workers, "baseline_tree": args.baseline_tree,
                                        "limit": limit}, figures, args.json_out,
                         what="How fast a live team keeps up: missed periods, CPU and latency at each speed-up.",
                         extra={"need_cpu_s_per_virtual_s": need, "runs": measured})


if __name__ == "__main__":
    main()
