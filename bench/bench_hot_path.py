"""CPU of the team's hot path per virtual second, in one process: load-independent, before vs after.

    .venv/bin/python bench/bench_hot_path.py [--virtual-s 60] [--baseline-tree DIR]

The paper's mission (paper-fig7, every component on the base station) runs its sources, stages
and sinks as the live processes do (`NodeRuntime`: produce, pad, encode, route, meter, custody,
decode, run, sink; statuses exchanged every 0.5 s of wall time at x50 for the custody acks), but
all four nodes in this process, on an in-memory bus and a manual clock, so the figure is CPU
time (not wall time) and the machine's load hardly moves it. Zenoh, TLS and the event loops
are not in it: `bench_live_speed.py` measures those live.

Printed per part: the components alone (the limit's need), the sources alone, and everything:
CPU ms per virtual second. With ``--baseline-tree DIR`` the same is measured on the code in DIR
(a checkout of the code before) in a child process, in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import results

SPEED = 50.0
STATUS_EVERY_WALL_S = 0.5


def measure(virtual_s: float) -> dict:
    from autopower.chains import make_component, make_source
    from autopower.model.loading import load_scenario
    from autopower.model.network import build_network
    from autopower.node.runtime import NodeRuntime
    from autopower.node.stages import chain_seed
    from autopower.protocol import Assign, Keys, LinkInfo, MissionInfo, PlanUpdate
    from autopower.runtime.bus import InMemoryHub
    from autopower.runtime.clock import ManualClock

    try:  # the team's processes set their allocator so (the code before did not)
        from autopower.runtime.memory import keep_large_buffers
    except ImportError:
        pass
    else:
        keep_large_buffers()
    sc = load_scenario("paper-fig7")
    net = build_network(sc, media={"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    links = tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in net.links)
    clock = ManualClock(speed=SPEED)
    hub, keys = InMemoryHub(), Keys("bench")
    placement = {c.stages[0].name: sc.basestation for c in sc.chains}
    mission = MissionInfo(scenario=sc.name, accounting=sc.accounting, epoch_unix=clock.epoch_unix, speed=SPEED,
                          energies_j=sc.energies_j())
    nodes = {}
    for name in sc.node_names():
        bus = hub.bus(name)
        rt = NodeRuntime(node=name, scenario=sc, bus=bus, keys=keys, clock_factory=lambda m: clock,
                         make_component=make_component, make_source=make_source, wall=clock.wall)
        for key in (keys.node_data(name), keys.node_control(name)):
            bus.subscribe(key, lambda k, p, rt=rt: rt.on_message(k, p))
        nodes[name] = rt
    for rt in nodes.values():
        for other in nodes:
            if other != rt.node:
                rt.on_liveliness(other, True)
        rt.on_plan(PlanUpdate(epoch=1, mission=mission, placement=placement, running={c.name: 0 for c in sc.chains},
                              links=links, predicted_w={}, predicted_lifetime_s=None, plan_t_virtual=0.0))
    for chain in sc.chains:
        nodes[sc.basestation].on_assign(Assign(stage=chain.stages[0].name, generation=1, chain=chain.name, run=0,
                                               resume_seq=0))

    # the components and sources alone, on the same inputs (the need the limit is computed from)
    comp_s = src_s = 0.0
    for chain in sc.chains:
        seed = chain_seed(sc, chain)
        source = make_source(chain.stages[0].component, chain.source, seed)
        component = make_component(chain.stages[0].component, chain.source, seed)
        runs = int(virtual_s / chain.period_s)
        t = time.process_time()
        inputs = [source.produce(i) for i in range(runs)]
        src_s += time.process_time() - t
        t = time.process_time()
        for data in inputs:
            component.run(data)
        comp_s += time.process_time() - t

    status_every_v = STATUS_EVERY_WALL_S * SPEED
    next_status = 0.0
    t = time.process_time()
    while clock.t < virtual_s:
        due = [d for rt in nodes.values() if (d := rt.next_deadline()) is not None]
        clock.set(max(clock.t, min(min(due, default=virtual_s), next_status, virtual_s)))
        for rt in nodes.values():
            rt.on_timer()
        if clock.t >= next_status:
            statuses = [rt.status(2.0 * SPEED) for rt in nodes.values()]
            for rt in nodes.values():
                for status in statuses:
                    if status.node != rt.node:
                        rt.on_peer_status(status)
            next_status += status_every_v
    total_s = time.process_time() - t
    outputs = sum(ledger.received_total for rt in nodes.values() for ledger in rt.sinks.values())
    errors = {n: rt.errors for n, rt in nodes.items() if rt.errors}
    return {"virtual_s": virtual_s, "components_ms": comp_s / virtual_s * 1e3, "sources_ms": src_s / virtual_s * 1e3,
            "total_ms": total_s / virtual_s * 1e3, "outputs": outputs, "errors": errors,
            "custody_frames": sum(len(rt.custody) for rt in nodes.values())}


def show(label: str, r: dict) -> None:
    runtime = r["total_ms"] - r["components_ms"] - r["sources_ms"]
    print(f"{label:8} {r['components_ms']:>12.2f} {r['sources_ms']:>10.2f} {runtime:>10.2f} {r['total_ms']:>10.2f} "
          f"{r['outputs']:>8} {r['total_ms'] / r['components_ms']:>12.2f} {r['custody_frames']:>9}"
          f"  {'errors: ' + str(r['errors']) if r['errors'] else ''}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--virtual-s", type=float, default=60.0)
    ap.add_argument("--baseline-tree", default=None, metavar="DIR")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    results.add_json_out(ap)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.virtual_s)))
        return
    print(f"== hot path CPU per virtual second, paper-fig7 (all on the base station), {args.virtual_s:g} virtual s, "
          f"load average {os.getloadavg()[0]:.2f} ==")
    print(f"{'code':8} {'components ms':>12} {'sources ms':>10} {'runtime ms':>10} {'total ms':>10} {'outputs':>8} "
          f"{'total/comp.':>12} {'unacked':>9}")
    before = None
    if args.baseline_tree:
        env = {**os.environ, "PYTHONPATH": args.baseline_tree}
        out = subprocess.run([sys.executable, __file__, "--child", "--virtual-s", str(args.virtual_s)], env=env,
                             capture_output=True, text=True, check=True).stdout
        before = json.loads(out.strip().splitlines()[-1])
        show("before", before)
    after = measure(args.virtual_s)
    show("after", after)
    print("runtime = everything but the components' and the sources' own calls (produce, run): per-frame work of "
          "the nodes (encode/decode, padding, routing, meter, custody, sequencing, sinks, statuses)")
    comp = after["components_ms"]
    note = "the mission's components alone on the same inputs, CPU ms per virtual second (the limit's need)"
    figures = [
        results.figure("everything (four nodes in one process)", after["total_ms"], "CPU ms per virtual s",
                       "components alone", comp, note=note),
        results.figure("runtime (all but the components and the sources)",
                       after["total_ms"] - comp - after["sources_ms"], "CPU ms per virtual s", "components alone",
                       comp, note=note),
        results.figure("sources alone", after["sources_ms"], "CPU ms per virtual s", "components alone", comp,
                       note=note),
    ]
    if before is not None:
        figures.append(results.figure("everything (four nodes in one process)", after["total_ms"],
                                      "CPU ms per virtual s", "code before", before["total_ms"],
                                      group="against the code before",
                                      note=f"the same on --baseline-tree {args.baseline_tree}"))
    results.write_result("hot_path", {"virtual_s": args.virtual_s, "speed": SPEED,
                                      "baseline_tree": args.baseline_tree}, figures, args.json_out,
                         what="CPU of the team's hot path per virtual second, the four nodes of the paper's mission "
                              "in one process (load-independent), against the components alone.",
                         extra={"after": after, "before": before})


if __name__ == "__main__":
    main()
