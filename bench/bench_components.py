"""Measure the real components on this machine (the paper's Fig. 5 numbers for this platform).

    .venv/bin/python bench/bench_components.py [runs] [--baseline-tree DIR]

Each component runs its source's messages for seq 0..runs-1 (`autopower.chains.profile_components`).
With ``--baseline-tree DIR`` (a checkout of the code before: ``git archive REV | tar -x -C DIR``)
the same is measured on that code in a child process, alternating with this one three times, and
each component's median is printed against the baseline's (after / before, the medians of the
three rounds: the machine's load falls on both alike).
"""

import argparse
import json
import os
import statistics
import subprocess
import sys

import results

from autopower.chains import profile_components

ROUNDS = 3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="?", type=int, default=50)
    ap.add_argument("--baseline-tree", default=None, metavar="DIR")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # the baseline's run: JSON out
    results.add_json_out(ap)
    args = ap.parse_args()
    if not 1 <= args.runs <= 100_000:
        raise SystemExit("runs must be within 1..100000")
    if args.child:
        print(json.dumps(profile_components(args.runs)))
        return
    if not args.baseline_tree:
        print(f"{'component':<10}{'mean ms':>10}{'median ms':>11}{'max ms':>9}{'in B':>9}{'out B':>8}")
        profile = profile_components(args.runs)
        for name, p in profile.items():
            print(f"{name:<10}{p['latency_mean_s'] * 1e3:>10.2f}{p['latency_median_s'] * 1e3:>11.2f}"
                  f"{p['latency_max_s'] * 1e3:>9.2f}{p['input_bytes']:>9}{p['output_bytes']:>8}")
        write(args, {name: p["latency_median_s"] for name, p in profile.items()}, None)
        return
    env = {**os.environ, "PYTHONPATH": os.path.abspath(args.baseline_tree)}
    now: dict[str, list[float]] = {}
    before: dict[str, list[float]] = {}
    for _ in range(ROUNDS):
        child = subprocess.run([sys.executable, __file__, str(args.runs), "--child"], env=env,
                               capture_output=True, text=True, check=True)
        for name, p in json.loads(child.stdout).items():
            before.setdefault(name, []).append(p["latency_median_s"])
        for name, p in profile_components(args.runs).items():
            now.setdefault(name, []).append(p["latency_median_s"])
    print(f"{'component':<10}{'median ms':>11}{'before ms':>11}{'after/before':>14}   (median of {ROUNDS} alternating rounds)")
    for name, medians in now.items():
        after_ms = statistics.median(medians) * 1e3
        line = f"{name:<10}{after_ms:>11.2f}"
        if name in before:
            before_ms = statistics.median(before[name]) * 1e3
            line += f"{before_ms:>11.2f}{after_ms / before_ms:>14.2f}"
        print(line)
    write(args, {n: statistics.median(m) for n, m in now.items()}, {n: statistics.median(m) for n, m in before.items()})


def write(args, medians: dict[str, float], before: dict[str, float] | None) -> None:
    """Each component's median run against the laptop latency the scenario declares (the paper's Fig. 5
    for Loc and Blob), and against the code before when it was measured."""
    from autopower.model.loading import load_scenario

    declared = {}
    for scenario in ("paper-fig7", "paper-teammap"):
        for name, spec in load_scenario(scenario).components.items():
            declared.setdefault(name, (scenario, spec.latency_s.get("laptop")))
    figures = []
    for name, median in medians.items():
        scenario, laptop = declared.get(name, (None, None))
        if laptop is not None:
            paper = scenario == "paper-fig7"
            figures.append(results.figure(
                f"{name}, median run", median * 1e3, "ms", "the paper's laptop" if paper else "declared laptop",
                laptop * 1e3, note="the laptop latency the paper measured (Fig. 5), in paper-fig7" if paper else
                f"the laptop latency {scenario} declares (an estimate, not the paper's)"))
        if before and name in before:
            figures.append(results.figure(f"{name}, median run", median * 1e3, "ms", "code before",
                                          before[name] * 1e3, group="against the code before",
                                          note=f"the same on --baseline-tree {args.baseline_tree}"))
    results.write_result("components", {"runs": args.runs, "baseline_tree": args.baseline_tree}, figures,
                         args.json_out, what=__doc__.splitlines()[0])


if __name__ == "__main__":
    main()
