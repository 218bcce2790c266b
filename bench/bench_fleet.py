"""Live fleets beyond the paper's trio: `autopower up` on generated teams of N robots. Not a timed test.

    .venv/bin/python bench/bench_fleet.py [--robots 3,10,20,30,50] [--seconds 30] [--speed 1]
                                          [--topology neighbours] [--neighbours 2] [--keep DIR]

Each team is `autopower scenarios fleet N --topology T` (every robot the paper's camera robot: a Loc
chain and a 4 Hz Blob chain each; by default each robot links to the base station and its two ring
neighbours on either side, the links a fleet's Zenoh sessions follow; 802.11a or GSM to the base
station, 802.11a or Bluetooth between robots, the planner's choice), run by the installed
CLI as a user runs it, every process real and every link through its proxy, for ``--seconds`` of
wall time at ``--speed``. The first size is the baseline measured in the same run (3 robots: the
paper's team size). Printed per size: the time until the team is ready, the periods missed, the
CPU the whole team used (every process, per wall second and per robot), the outputs its sinks
took in with any gap or second copy, the largest gap between a robot's metered power and the
model's, whether every process stopped by itself, the largest process's memory (peak RSS), the
messages the base station's event queue dropped, and per process: the base station's CPU and the
busiest agent's (each from its status: since the mission started) and their peak memory, and per
robot the packets (TCP segments, bare acknowledgements included) and bytes its links carried a second,
as its own kernel counted them, and of the bytes the control plane's. A team
that is not ready within the time `up` allows is reported as such, with the base station's last
log lines that say why.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results as bench_results

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def peak_rss_kb(pid: int) -> int:
    """A live process's peak resident memory (the kernel's VmHWM), 0 once it is gone."""
    try:
        return bench_results.proc_status_kb(pid, "VmHWM") or 0
    except OSError:
        return 0


def run_up(args: list[str], env: dict, timeout_s: float, out_path: Path,
           session_file: Path) -> tuple[int, float, int, dict[str, int]]:
    """Run `autopower up`, stdout to ``out_path``: (exit code, CPU s, peak RSS in KB) of it and every
    process it started (`wait4` sums what its children used; the RSS is the largest one's), and the
    peak RSS in KB of each node's process, read while it runs (the nodes' pids from up's session)."""
    with open(out_path, "wb") as out:
        proc = subprocess.Popen([AUTOPOWER, "up", *args], env=env, stdout=out, stderr=subprocess.DEVNULL,
                                stdin=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout_s
    children: dict[str, int] = {}
    peaks: dict[str, int] = {}
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        if time.monotonic() > deadline:
            proc.kill()
        if not children:
            try:
                children = {node: int(p) for node, p in json.loads(session_file.read_text())["children"].items()}
            except (OSError, ValueError, KeyError):
                pass  # not written yet
        for node, child in children.items():
            peaks[node] = max(peaks.get(node, 0), peak_rss_kb(child))
        time.sleep(0.2)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_utime + usage.ru_stime, usage.ru_maxrss, peaks


def queue_drops(summary: dict) -> int:
    errors = (summary.get("basestation") or {}).get("errors") or {}
    return int(errors.get("queue-full", 0))


def why_not_ready(log_dir: Path) -> str:
    """The base station's warnings (a full event queue, …) and its last line: why a team never got ready."""
    try:
        lines = (log_dir / "laptop.log").read_text(errors="replace").splitlines()
    except OSError:
        return ""
    warnings = [l.split(": ", 1)[-1] for l in lines if " WARNING " in l]
    return "; ".join(dict.fromkeys(w[:100] for w in warnings[-2:])) or (lines[-1][-120:] if lines else "")


def run_fleet(n: int, seconds: float, speed: float, folder: Path, topology: str, neighbours: int,
              up_args: tuple[str, ...] = ()) -> dict:
    env = {**os.environ, "AUTOPOWER_STATE_DIR": str(folder / f"state-{n}"), "RERUN_ANALYTICS": "0"}
    scenario = folder / f"fleet-{n}.toml"
    subprocess.run([AUTOPOWER, "scenarios", "fleet", str(n), "--topology", topology, "--neighbours", str(neighbours),
                    "--out", str(scenario)], env=env, check=True, capture_output=True, timeout=120)
    started = time.monotonic()
    log_dir = folder / f"logs-{n}"
    team = f"fleet-{n}"
    code, cpu, rss_kb, peaks = run_up(
        [str(scenario), "--team", team, "--speed", f"{speed:g}", "--duration", f"{seconds:g}", "--json",
         "--log-dir", str(log_dir), *up_args], env, seconds + 600, folder / f"up-{n}.json",
        Path(env["AUTOPOWER_STATE_DIR"]) / "teams" / team / "session.json")
    wall = time.monotonic() - started
    text = (folder / f"up-{n}.json").read_text(errors="replace")
    try:
        summary = json.loads(text)
    except json.JSONDecodeError:
        summary = {"error": text[-300:]}
    out = {"robots": n, "exit": code, "wall_s": wall, "cpu_s": cpu, "ready": bool(summary.get("ready")),
           "peak_rss_mb": rss_kb / 1024, "queue_drops": queue_drops(summary)}
    if not out["ready"]:
        out["error"] = str(summary.get("error", ""))[:120].replace("\n", " ")
        out["why"] = why_not_ready(log_dir)
        return out
    sinks = {**summary["basestation"]["sinks"],
             **{c: s for r in summary["robots"].values() for c, s in r["sinks"].items()}}
    run_wall = wall - summary["ready_after_s"]
    robots = list(summary["robots"])
    # each process's CPU over the mission's wall time (its status counts from the mission's start)
    mission_wall = (summary.get("t_virtual") or 0.0) / speed

    def cores(cpu_s: dict | None) -> float:
        return sum((cpu_s or {}).values()) / mission_wall if mission_wall > 0 else 0.0

    agent_cores = [cores(r.get("cpu_s")) for r in summary["robots"].values()]
    base_name = next((node for node in peaks if node not in summary["robots"]), None)
    agent_peaks = [kb for node, kb in peaks.items() if node in summary["robots"]]
    per_robot = [sum(b for pair, b in summary.get("link_bytes", {}).items() if r in pair.split("-")) for r in robots]
    # each robot's own count of its links (its kernel's), per second of the mission's wall time
    own = [r.get("links") or {} for r in summary["robots"].values()]

    def per_s(what: str) -> list[float]:
        return [(o.get(f"{what}_sent", 0) + o.get(f"{what}_received", 0)) / mission_wall if mission_wall > 0 else 0.0
                for o in own]
    out.update(ready_after_s=summary["ready_after_s"], missed_pct=summary["missed_periods_pct"],
               outputs=sum(s["received"] for s in sinks.values()),
               gaps=sum(s["max_seq"] + 1 - s["contiguous"] for s in sinks.values()),
               duplicates=sum(s["duplicates_total"] for s in sinks.values()),
               power_error_pct=100 * max((abs(r["power_error"]) for r in summary["robots"].values()
                                         if r["power_error"] is not None), default=0.0),
               # a robot with no comparison (not on the plan when the team got ready, or gone since)
               unmetered=sorted(n for n, r in summary["robots"].items() if r["power_error"] is None),
               clean=all(code == 0 for code in summary["exit_codes"].values()),
               cores=cpu / wall, run_wall_s=run_wall,
               robot_kbps=max(per_robot, default=0) / wall / 1e3 * 8,
               robot_links=max((sum(r in p.split("-") for p in summary.get("link_bytes", {})) for r in robots),
                               default=0),
               basestation_cores=cores(summary["basestation"].get("cpu_s")),
               agent_cores_max=max(agent_cores, default=0.0),
               agent_cores_mean=sum(agent_cores) / len(agent_cores) if agent_cores else 0.0,
               basestation_peak_mb=peaks.get(base_name, 0) / 1024 if base_name else 0.0,
               agent_peak_mb_max=max(agent_peaks, default=0) / 1024,
               robot_packets_per_s_max=max(per_s("packets"), default=0.0),
               robot_packets_per_s_mean=sum(per_s("packets")) / len(own) if own else 0.0,
               robot_bytes_per_s_mean=sum(per_s("bytes")) / len(own) if own else 0.0,
               robot_control_bytes_per_s_mean=sum(per_s("control_bytes")) / len(own) if own else 0.0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", default="3,10,20,30,50")
    parser.add_argument("--topology", default="neighbours", choices=["neighbours", "fully-connected", "relay"])
    parser.add_argument("--neighbours", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--speed", type=float, default=1.0)
    parser.add_argument("--robot-nice", type=int, default=None, help="up's --robot-nice (default: up's own)")
    parser.add_argument("--keep", type=Path, default=None,
                        help="run in this folder and keep it (scenarios, every process's log, up's JSON)")
    bench_results.add_json_out(parser)
    args = parser.parse_args()
    sizes = [int(x) for x in args.robots.split(",")]
    up_args = () if args.robot_nice is None else ("--robot-nice", str(args.robot_nice))
    if args.keep is not None:
        args.keep.mkdir(mode=0o700, parents=True, exist_ok=True)
        runs = [run_fleet(n, args.seconds, args.speed, args.keep, args.topology, args.neighbours, up_args)
                for n in sizes]
    else:
        with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
            runs = [run_fleet(n, args.seconds, args.speed, Path(tmp), args.topology, args.neighbours, up_args)
                    for n in sizes]
    base = runs[0]
    print(f"{'robots':>6} {'ready s':>8} {'missed %':>9} {'cores':>6} {'CPU s/robot':>12} {'outputs':>8} "
          f"{'gaps':>5} {'dups':>5} {'|power err| %':>14} {'clean':>6} {'peak MB':>8} {'drops':>6} {'robot kbit/s':>13} "
          f"{'base cores':>11} {'agent cores':>12} {'base MB':>8} {'agent MB':>9} {'robot pkt/s':>12} {'robot B/s':>10} "
          f"{'of it control':>14}")
    for r in runs:
        if not r["ready"]:
            print(f"{r['robots']:>6} not ready ({r['error'][:90]}) {r['why']}")
            continue
        print(f"{r['robots']:>6} {r['ready_after_s']:>8.1f} {r['missed_pct']:>9.2f} {r['cores']:>6.2f} "
              f"{r['cpu_s'] / r['robots']:>12.2f} {r['outputs']:>8} {r['gaps']:>5} {r['duplicates']:>5} "
              f"{r['power_error_pct']:>14.2f} {str(r['clean']):>6} {r['peak_rss_mb']:>8.0f} {r['queue_drops']:>6} {r['robot_kbps']:>13.0f} "
              f"{r['basestation_cores']:>11.3f} {r['agent_cores_max']:>12.3f} {r['basestation_peak_mb']:>8.0f} "
              f"{r['agent_peak_mb_max']:>9.0f} {r['robot_packets_per_s_mean']:>12.0f} {r['robot_bytes_per_s_mean']:>10.0f} "
              f"{r['robot_control_bytes_per_s_mean']:>14.0f}")
    note = f"the {base['robots']}-robot fleet, run the same way in the same run"
    figures = []
    for r in runs[1:]:
        g = f"{r['robots']} robots"
        if not r["ready"]:
            figures.append(bench_results.figure("ready (1: yes, 0: no)", 0, "", f"{base['robots']} robots",
                                                1 if base["ready"] else 0, group=g, note=note,
                                                detail=f"not ready within the time `up` allows: {r['why'] or r['error']}"))
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
                                 f"{base['robots']} robots", base["power_error_pct"], group=g, note=note,
                                 detail=(f"{len(r['unmetered'])} robot(s) without a comparison: "
                                         f"{', '.join(r['unmetered'][:5])}") if r["unmetered"] else ""),
            bench_results.figure("processes that did not stop by themselves", 0 if r["clean"] else 1, "teams",
                                 f"{base['robots']} robots", 0 if base["clean"] else 1, group=g, note=note),
            bench_results.figure("the busiest robot's radio traffic, all its links", r["robot_kbps"], "kbit/s",
                                 f"{base['robots']} robots", base["robot_kbps"], group=g, note=note,
                                 detail=f"over {r['robot_links']} links at most (wire bytes: data, statuses, "
                                        f"keep-alives, TLS), the whole run"),
            bench_results.figure("largest process's peak memory", r["peak_rss_mb"], "MB", f"{base['robots']} robots",
                                 base["peak_rss_mb"], group=g, note=note),
            bench_results.figure("the base station's CPU", r["basestation_cores"], "cores",
                                 f"{base['robots']} robots", base["basestation_cores"], group=g, note=note,
                                 detail="its process since the mission started: runtime and the stages it hosts"),
            bench_results.figure("the busiest agent's CPU", r["agent_cores_max"], "cores",
                                 f"{base['robots']} robots", base["agent_cores_max"], group=g, note=note,
                                 detail=f"mean of the agents {r['agent_cores_mean']:.3f} cores"),
            bench_results.figure("the base station's peak memory", r["basestation_peak_mb"], "MB",
                                 f"{base['robots']} robots", base["basestation_peak_mb"], group=g, note=note),
            bench_results.figure("the largest agent's peak memory", r["agent_peak_mb_max"], "MB",
                                 f"{base['robots']} robots", base["agent_peak_mb_max"], group=g, note=note),
            bench_results.figure("messages the base station's queue dropped", r["queue_drops"], "messages",
                                 f"{base['robots']} robots", base["queue_drops"], group=g, note=note),
            bench_results.figure("packets a robot's links carry a second (mean)", r["robot_packets_per_s_mean"],
                                 "packets/s", f"{base['robots']} robots", base["robot_packets_per_s_mean"], group=g,
                                 note=note, detail=f"busiest robot {r['robot_packets_per_s_max']:.0f}/s; TCP segments "
                                                   "both ways, as each robot's kernel counted them"),
            bench_results.figure("bytes a robot's links carry a second (mean)", r["robot_bytes_per_s_mean"], "B/s",
                                 f"{base['robots']} robots", base["robot_bytes_per_s_mean"], group=g, note=note,
                                 detail=f"of which the control plane {r['robot_control_bytes_per_s_mean']:.0f} B/s"),
        ]
    bench_results.write_result("fleet", {"robots": sizes, "seconds": args.seconds, "speed": args.speed,
                                         "topology": args.topology, "neighbours": args.neighbours}, figures,
                               args.json_out, what=__doc__.splitlines()[0], extra={"runs": runs})


if __name__ == "__main__":
    main()
