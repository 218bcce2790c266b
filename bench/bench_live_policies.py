"""Live missions under two policies: does the policy code extend the real team's lifetime?

    .venv/bin/python bench/bench_live_policies.py [--energy-scale 0.01] [--speed 10] [--topology relay]

Runs the paper's mission twice on a real localhost team (`autopower up ... --until-depleted`):
once with ``static`` (the baseline, same run) and once with ``rebalance``, and prints each
mission's measured lifetime (virtual seconds until the first robot is empty), the migrations
the base station made and the lifetime the simulator predicts for the same scenario and policy.
In the relay topology the time-sharing schedule beats the best fixed plan by ~2.8 % (the model);
this measures what a live team gets. Not a test: prints figures. Bounded: each mission stops
when the first robot is empty, or after ``--max-wall`` seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import results

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

AUTOPOWER = str(ROOT / ".venv" / "bin" / "autopower")


def live(policy: str, args) -> dict:
    with tempfile.TemporaryDirectory(prefix=f"ap-live-{policy}-") as tmp:
        env = {**os.environ, "AUTOPOWER_STATE_DIR": tmp, "RERUN_ANALYTICS": "0"}
        cmd = [AUTOPOWER, "up", "paper-fig7", "--topology", args.topology, "--policy", policy,
               "--energy-scale", str(args.energy_scale), "--speed", str(args.speed), "--until-depleted",
               "--duration", str(args.max_wall), "--json", "--log-dir", str(Path(tmp) / "logs")]
        result = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.max_wall + 120)
        if result.returncode != 0:
            raise SystemExit(f"{policy}: autopower up failed:\n{result.stderr[-2000:]}")
        return json.loads(result.stdout)


def simulated(policy: str, args) -> float:
    from autopower.model.loading import load_scenario
    from autopower.simulation.simulator import simulate

    s = load_scenario("paper-fig7")
    s = s.with_energies({r.name: r.energy_j * args.energy_scale for r in s.robots})
    return simulate(s, policy=policy, topology=args.topology).lifetime_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--energy-scale", type=float, default=0.01)
    parser.add_argument("--speed", type=float, default=10.0)
    parser.add_argument("--topology", default="relay")
    parser.add_argument("--max-wall", type=float, default=600.0)
    results.add_json_out(parser)
    args = parser.parse_args()
    if not 0.001 <= args.energy_scale <= 0.05 or not 1 <= args.speed <= 40:
        raise SystemExit("--energy-scale must be within 0.001..0.05 and --speed within 1..40")
    rows = {}
    for policy in ("static", "rebalance"):
        summary = live(policy, args)
        first = summary.get("first_depletion") or {}
        rows[policy] = {"lifetime_s": first.get("t_virtual"), "robot": first.get("robot"),
                        "migrations": summary.get("migrations_done"), "missed": summary.get("missed_ratio"),
                        "simulated_s": simulated(policy, args)}
    print(f"paper-fig7, {args.topology}, batteries x{args.energy_scale:g}, speed {args.speed:g}x")
    print(f"{'policy':10} {'live lifetime s':>16} {'first dry':>9} {'migrations':>10} {'missed':>7} "
          f"{'simulated s':>12}")
    for policy, r in rows.items():
        life = f"{r['lifetime_s']:.1f}" if r["lifetime_s"] is not None else "—"
        print(f"{policy:10} {life:>16} {r['robot'] or '—':>9} {r['migrations']:>10} {r['missed'] or 0:>7.1%} "
              f"{r['simulated_s']:>12.1f}")
    a, b = rows["static"]["lifetime_s"], rows["rebalance"]["lifetime_s"]
    if a and b:
        print(f"live rebalance / static: {b / a:.4f}x   (simulated: "
              f"{rows['rebalance']['simulated_s'] / rows['static']['simulated_s']:.4f}x)")
    g = f"paper-fig7, {args.topology}, batteries x{args.energy_scale:g}, x{args.speed:g}"
    figures = [
        results.figure("rebalance, live lifetime", b, "s", "static, live", a, group=g,
                       note="the same mission live under the static policy, same run",
                       detail=f"{rows['rebalance']['migrations']} migrations"),
        results.figure("rebalance, simulated lifetime", rows["rebalance"]["simulated_s"], "s", "static, simulated",
                       rows["static"]["simulated_s"], group=g, note="the simulator, same scenario, static policy"),
    ]
    for policy, r in rows.items():
        figures.append(results.figure(f"{policy}, live lifetime", r["lifetime_s"], "s", "simulated",
                                      r["simulated_s"], group=g, detail=f"first empty: {r['robot']}",
                                      note="the simulator's lifetime for the same scenario and policy"))
    results.write_result("live_policies", {"energy_scale": args.energy_scale, "speed": args.speed,
                                           "topology": args.topology, "max_wall": args.max_wall}, figures,
                         args.json_out, what=__doc__.splitlines()[0], extra=rows)


if __name__ == "__main__":
    main()
