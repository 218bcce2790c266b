"""Fault detection and reconfiguration on a real team, against a raw-liveliness baseline.

    .venv/bin/python bench/bench_faults.py [--cuts 20] [--speed 5]

One team (base station + three agents, every link through its LinkProxy, lease 500 ms). Each
round cuts r1's link to the base station silently, waits for the base station to record the
fault as handled (detection: it lost sight of r1 or heard so from r1; reconfigured: the new
plan runs and every robot in reach runs its epoch — r1 through a relay), then heals and waits
for the link to be back in the plan (hysteresis hold included). The baseline, measured in the
same run: two bare Zenoh sessions through a LinkProxy with the same lease, idle, cut the same
way — the floor any detection built on the lease can reach. Not a test: prints figures.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import results

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LEASE_MS = 500


def _zenoh_config(listen=None, connect=None):
    import zenoh

    c = zenoh.Config()
    for key, value in {
        "mode": '"peer"', "scouting/multicast/enabled": "false", "scouting/gossip/enabled": "false",
        "listen/endpoints": f'["tcp/127.0.0.1:{listen}"]' if listen else "[]",
        "connect/endpoints": f'["tcp/127.0.0.1:{connect}"]' if connect else "[]",
        "transport/link/tx/lease": str(LEASE_MS), "transport/link/tx/keep_alive": "4",
        "connect/retry": "{period_init_ms: 50, period_max_ms: 200, period_increase_factor: 2}",
        "connect/timeout_ms": "-1",
    }.items():
        c.insert_json5(key, value)
    return c


FAR_SIDE = """
import sys, time, zenoh
c = zenoh.Config()
for k, v in [("mode", '"peer"'), ("scouting/multicast/enabled", "false"), ("scouting/gossip/enabled", "false"),
             ("listen/endpoints", "[]"), ("connect/endpoints", f'["tcp/127.0.0.1:{sys.argv[1]}"]'),
             ("transport/link/tx/lease", sys.argv[2]), ("transport/link/tx/keep_alive", "4"),
             ("connect/retry", "{period_init_ms: 50, period_max_ms: 200, period_increase_factor: 2}"),
             ("connect/timeout_ms", "-1")]:
    c.insert_json5(k, v)
s = zenoh.open(c)
tok = s.liveliness().declare_token("bf/far")
time.sleep(float(sys.argv[3]))  # bounded: never outlives the benchmark
"""


def baseline(cuts: int) -> list[float]:
    """Raw liveliness detection of a silent cut on an idle pair of processes through a proxy."""
    import subprocess

    import zenoh

    from autopower.launch.linkproxy import LinkProxy, free_port

    port = free_port()
    near = zenoh.open(_zenoh_config(listen=port))
    events = []
    near.liveliness().declare_subscriber("bf/**", lambda s: events.append((time.monotonic(), s.kind)), history=True)
    out = []
    with LinkProxy("baseline", port) as proxy:
        far = subprocess.Popen([sys.executable, "-c", FAR_SIDE, str(proxy.port), str(LEASE_MS), str(20 + 3 * cuts)])
        try:
            _until(lambda: any(k == zenoh.SampleKind.PUT for _, k in events), 10)
            for _ in range(cuts):
                events.clear()
                proxy.cut()
                t0 = time.monotonic()
                if _until(lambda: any(k == zenoh.SampleKind.DELETE for _, k in events), 5):
                    out.append(next(t for t, k in events if k == zenoh.SampleKind.DELETE) - t0)
                events.clear()
                proxy.heal()
                _until(lambda: any(k == zenoh.SampleKind.PUT for _, k in events), 5)
        finally:
            far.kill()
            far.wait()
            near.close()
    return out


def _until(predicate, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return False


def delivery(snap: dict) -> dict[str, float]:
    """Exactly-once figures over the whole team: what custody resent, what the sinks still lack."""
    from autopower.launch.summary import lost_outputs, team_sinks

    statuses = [v["status"] for v in snap["robots"].values() if v.get("status")]
    if snap.get("basestation"):
        statuses.append(snap["basestation"])
    sinks = team_sinks(snap)
    counters = [s["counters"] for s in statuses]
    return {
        "outputs": sum(st["received_total"] for st in sinks),
        "lost": lost_outputs(sinks),
        "duplicated": sum(st["duplicates_total"] for st in sinks),
        "redundant": sum(st.get("redundant_total", 0) for st in sinks),
        "resent": sum(c.get("custody-resent", 0) for c in counters),
        "second_inputs": sum(s["errors"].get("duplicate-input", 0) for s in statuses),
        "recovered": sum(c.get("recovered-outputs", 0) for c in counters),
        "latency_ms_max": max((st["latency_ms_max"] for st in sinks), default=0.0),
    }


def team_cuts(cuts: int, speed: float) -> tuple[list[float], list[float], dict]:
    from autopower.cli.options import build_scenario
    from autopower.launch.faults import FaultController
    from autopower.launch.localhost import LocalTeam, TeamSpec

    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=speed, lease_ms=LEASE_MS, proxied_links=True)
    detected, reconfigured = [], []
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        faults = FaultController(team)
        for i in range(cuts):
            before = len(team.snapshot()["faults"])
            t0 = faults.apply({"op": "cut", "a": "r1", "b": "laptop"})["fault"]["t_unix"]
            fault = None
            end = time.monotonic() + 10
            while fault is None and time.monotonic() < end:
                snap = team.snapshot()
                fault = next((f for f in snap["faults"][before:] if f["kind"] == "link-down"
                              and f["reconfigured_unix"]), None)
                time.sleep(0.02)
            if fault is None:
                print(f"  cut {i + 1}: not handled within 10 s", file=sys.stderr)
            else:
                detected.append(fault["detected_unix"] - t0)
                reconfigured.append(fault["reconfigured_unix"] - t0)
            faults.apply({"op": "heal", "a": "r1", "b": "laptop"})
            end = time.monotonic() + 15
            while time.monotonic() < end and team.snapshot()["links_down"]:
                time.sleep(0.05)
        time.sleep(3.0)  # the last losses' reports and resends
        figures = delivery(team.snapshot())
    return detected, reconfigured, figures


def subgroup_rounds(rounds: int, speed: float) -> list[float]:
    """Cut every robot from the base station, wait for the subgroup to commit, heal; repeat.

    The figure is the leader's propose -> commit time (every member's vote in), as it reports it.
    """
    from autopower.cli.options import build_scenario
    from autopower.launch.faults import FaultController
    from autopower.launch.localhost import LocalTeam, TeamSpec

    scenario = build_scenario("paper-fig7")
    spec = TeamSpec(scenario="paper-fig7", speed=speed, lease_ms=LEASE_MS, proxied_links=True)
    robots = [r.name for r in scenario.robots]
    out = []
    with LocalTeam(spec, scenario) as team:
        team.wait_ready(60)
        faults = FaultController(team)
        commits = 0
        for i in range(rounds):
            for r in robots:
                faults.apply({"op": "cut", "a": r, "b": "laptop"})
            time.sleep(2.5)  # detection (~0.5 s), settle, one round; the base cannot see it now
            for r in robots:
                faults.apply({"op": "heal", "a": r, "b": "laptop"})
            end = time.monotonic() + 20
            snap = {}
            while time.monotonic() < end:
                snap = team.snapshot()
                st = (snap["robots"]["r1"] or {}).get("status") or {}
                if snap["ready"] and all(v["present"] for v in snap["robots"].values()) \
                        and st.get("counters", {}).get("subgroup-commits", 0) > commits:
                    break
                time.sleep(0.1)
            counters = snap["robots"]["r1"]["status"]["counters"]
            if counters.get("subgroup-commits", 0) > commits:
                commits = counters["subgroup-commits"]
                out.append(counters.get("subgroup-agreement-us", 0) / 1e6)
            else:
                print(f"  subgroup round {i + 1}: no commit seen", file=sys.stderr)
    return out


def _fmt(name: str, values: list[float]) -> str:
    if not values:
        return f"{name:<34} no samples"
    return (f"{name:<34} n={len(values):<3} median {statistics.median(values) * 1e3:7.1f} ms   "
            f"worst {max(values) * 1e3:7.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cuts", type=int, default=20)
    parser.add_argument("--baseline-cuts", type=int, default=10)
    parser.add_argument("--speed", type=float, default=5.0)
    parser.add_argument("--subgroup-rounds", type=int, default=5)
    results.add_json_out(parser)
    args = parser.parse_args()
    if not 1 <= args.cuts <= 200:
        raise SystemExit("--cuts must be within 1..200")
    base = baseline(args.baseline_cuts)
    detected, reconfigured, figures = team_cuts(args.cuts, args.speed)
    print(f"silent cuts of r1-laptop, lease {LEASE_MS} ms, speed {args.speed:g}x")
    print(_fmt("baseline: raw liveliness, idle", base))
    print(_fmt("team: detection", detected))
    print(_fmt("team: cut -> reconfigured", reconfigured))
    if base and detected:
        print(f"detection / baseline (median): {statistics.median(detected) / statistics.median(base):.2f}x")
    print(f"delivery over the cuts: {figures['outputs']} outputs; {figures['resent']} frames resent from custody "
          f"({figures['second_inputs']} of them, or their originals, arrived twice and were dropped by a stage; "
          f"{figures['recovered']} outputs reached a sink only by a resend); lost at the sinks {figures['lost']}, "
          f"duplicated {figures['duplicated']}, redundant copies dropped at sinks {figures['redundant']}; worst "
          f"output latency {figures['latency_ms_max']:.0f} ms")
    subgroup = []
    if args.subgroup_rounds > 0:
        subgroup = subgroup_rounds(min(args.subgroup_rounds, 20), args.speed)
        print(_fmt("subgroup agreement (2PC, 3 robots)", subgroup))
    def med(v: list[float]) -> float | None:
        return statistics.median(v) * 1e3 if v else None

    def worst(v: list[float]) -> float | None:
        return max(v) * 1e3 if v else None

    floor = f"raw liveliness (n={len(base)})"
    note = (f"two bare Zenoh sessions through a link proxy, lease {LEASE_MS} ms, idle, cut the same way: "
            "the floor of any detection built on the lease")
    g = f"silent cuts of r1-laptop, lease {LEASE_MS} ms, x{args.speed:g}"
    out = [
        results.figure(f"detection, median (n={len(detected)})", med(detected), "ms", floor, med(base), group=g,
                       note=note),
        results.figure("detection, worst", worst(detected), "ms", floor, worst(base), group=g, note=note),
        results.figure(f"cut to reconfigured, median (n={len(reconfigured)})", med(reconfigured), "ms", floor,
                       med(base), group=g, note=note),
        results.figure("cut to reconfigured, worst", worst(reconfigured), "ms", floor, worst(base), group=g,
                       note=note),
    ]
    if subgroup:
        out.append(results.figure(f"subgroup agreement (2PC, 3 robots), median (n={len(subgroup)})", med(subgroup),
                                  "ms", "the team's detection", med(detected), group=g,
                                  note="the team's median detection of a cut, same run"))
    for name, key in (("outputs lost at the sinks", "lost"), ("outputs duplicated at the sinks", "duplicated"),
                      ("frames resent from custody", "resent"), ("outputs that came only by a resend", "recovered")):
        out.append(results.figure(name, figures[key], "outputs", "outputs received", figures["outputs"],
                                  group="delivery over the cuts",
                                  note="every output the sinks received over the cuts"))
    results.write_result("faults", {"cuts": args.cuts, "baseline_cuts": args.baseline_cuts, "speed": args.speed,
                                    "subgroup_rounds": args.subgroup_rounds, "lease_ms": LEASE_MS}, out,
                         args.json_out, what=__doc__.splitlines()[0])


if __name__ == "__main__":
    main()
