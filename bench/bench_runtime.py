"""Runtime benchmarks: agent overhead per run, chain hop latency, migration downtime.

    .venv/bin/python bench/bench_runtime.py [overhead|hop|migration ...]

Not a timed test: each figure is printed beside a baseline measured in the same run (the bare
component call, a raw Zenoh echo (bench_relay.py), the chain's own period and latency), so the
ratios mean something on any machine. Absolute numbers are from whatever machine runs it.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import results

from autopower.chains import make_component, make_source
from autopower.cli.options import build_scenario
from autopower.launch.localhost import LocalTeam, TeamSpec
from autopower.model.energy import flow_weight
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.node.runtime import NodeRuntime
from autopower.node.stages import chain_seed
from autopower.protocol import (
    Assign,
    ChainFrame,
    Keys,
    LinkInfo,
    MigrateCommand,
    MissionInfo,
    Packet,
    PlanUpdate,
    encode,
)
from autopower.runtime.bus import InMemoryHub


def mission(scenario, speed=1.0) -> MissionInfo:
    return MissionInfo(scenario=scenario.name, accounting=scenario.accounting, epoch_unix=time.time(), speed=speed,
                       energies_j=scenario.energies_j())


def links(scenario) -> tuple[LinkInfo, ...]:
    net = build_network(scenario, media={"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    return tuple(LinkInfo(a=l.a, b=l.b, medium=l.medium) for l in net.links)


# ---------------------------------------------------------------------------------------------
# 1. agent overhead per component run
# ---------------------------------------------------------------------------------------------


class NullComponent:
    """Returns an output of the declared size at once: what is left is the agent's own work."""

    def __init__(self, out_size: int):
        self.out = bytes(out_size)

    def run(self, payload: bytes) -> bytes:
        return self.out

    def export_state(self) -> bytes:
        return b""

    def import_state(self, state: bytes) -> None:
        pass


def bench_overhead(runs: int = 300) -> list[dict]:
    scenario = load_scenario("paper-fig7")
    keys = Keys("bench")
    print("\n== agent overhead per component run (in-process) ==")
    print("baseline: the real component's bare run() on this machine; overhead: everything the agent does per "
          "input\n(decode packet, meter, sequence, pad, encode, route, publish), measured with a null component")
    print(f"{'chain':8} {'in B':>7} {'out B':>6} {'bare run ms':>12} {'agent overhead ms':>18} {'overhead/run':>13}")
    figures = []
    for name in ("Loc-2", "Blob-2"):
        chain = scenario.chain(name)
        seed = chain_seed(scenario, chain)
        source = make_source(chain.stages[0].component, chain.source, seed)
        inputs = [source.produce(i) for i in range(runs)]
        bare = make_component(chain.stages[0].component, chain.source, seed)
        times = []
        for data in inputs:
            started = time.perf_counter()
            bare.run(data)
            times.append(time.perf_counter() - started)
        bare_s = statistics.median(times)

        hub = InMemoryHub()
        out_size = chain.message_bytes[1]
        rt = NodeRuntime(node="r1", scenario=scenario, bus=hub.bus("r1"), keys=keys,
                         make_component=lambda *a: NullComponent(out_size), make_source=make_source)  # noqa: B023 (rt lives in this iteration)
        rt.on_plan(PlanUpdate(epoch=1, mission=mission(scenario), placement={name: "r1"}, running={},
                              links=links(scenario), predicted_w={}, predicted_lifetime_s=None, plan_t_virtual=0.0))
        rt.on_assign(Assign(stage=name, generation=1, chain=name, run=0, resume_seq=0))
        size = chain.message_bytes[0]
        packets = []
        for seq, data in enumerate(inputs):
            frame = ChainFrame(chain=name, run=0, seq=seq, target=0, t_virtual=0.0, t_unix=0.0,
                               payload_len=len(data), payload=data + bytes(size - len(data)))
            packets.append(encode(Packet(path=(chain.source, "r1"), media=("802.11a",), hop=1, charge_bytes=size,
                                         weight=flow_weight(chain, "paper"), purpose="chain", chain=name,
                                         body=encode(frame))))
        times = []
        for payload in packets:
            started = time.perf_counter()
            rt.on_data(payload)
            times.append(time.perf_counter() - started)
        agent_s = statistics.median(times)
        assert rt.hosted[name].runs == runs and not rt.errors, rt.errors
        print(f"{name:8} {size:>7} {out_size:>6} {bare_s * 1e3:>12.3f} {agent_s * 1e3:>18.3f} {agent_s / bare_s:>12.1%}")
        figures.append(results.figure(f"{name}: agent's work per input, median", agent_s * 1e3, "ms",
                                      "the component's bare run", bare_s * 1e3, group="agent overhead per run",
                                      note="the real component's run() alone on the same inputs, median"))
    return figures


# ---------------------------------------------------------------------------------------------
# 2. one relay hop vs raw zenoh: bench/bench_relay.py (also run as `hop` here)
# ---------------------------------------------------------------------------------------------


def bench_hop() -> list[dict]:
    from bench_relay import bench_relay  # bench/ is the script's directory: on sys.path

    return [dict(f, group="one relay hop") for f in bench_relay()]


# ---------------------------------------------------------------------------------------------
# 3. migration downtime
# ---------------------------------------------------------------------------------------------


def bench_migration(moves: int = 40, speed: float = 10.0) -> list[dict]:
    print(f"\n== migration downtime (real processes, speed x{speed:g}) ==")
    scenario = build_scenario("paper-fig7")
    with tempfile.TemporaryDirectory() as tmp:
        spec = TeamSpec(scenario="paper-fig7", speed=speed, auto_replan=False, log_dir=Path(tmp))
        with LocalTeam(spec, scenario) as team:
            team.wait_ready(60)
            time.sleep(3.0)
            base = team.snapshot()
            sinks0 = {**base["basestation"]["sinks"],
                      **{c: s for r in base["robots"].values() for c, s in r["status"]["sinks"].items()}}
            missed0 = sum(s["missed"] for r in base["robots"].values() for s in r["status"]["sources"].values())
            hosts = ["r1", "r2", "r3", "laptop"]
            issued = []
            for i in range(moves):
                for stage in ("Loc-2", "Blob-2"):
                    node = hosts[(i + (stage == "Blob-2")) % len(hosts)]
                    if team.snapshot()["placement"][stage] == node:
                        node = hosts[(i + 2) % len(hosts)]
                    started = time.perf_counter()
                    assert team.client.request(MigrateCommand(stage=stage, to_node=node)).ok
                    while True:
                        snap = team.snapshot()
                        if snap["placement"][stage] == node and snap["ready"]:
                            break
                    issued.append((stage, time.perf_counter() - started))
            time.sleep(1.0)
            end = team.snapshot()
            missed = sum(s["missed"] for r in end["robots"].values() for s in r["status"]["sources"].values()) - missed0
            log = end["migration_log"]
            print(f"{'stage':7} {'moves':>6} {'period ms':>10} {'steady latency p50 ms':>22} {'downtime p50 ms':>16} "
                  f"{'max ms':>7} {'p50 in periods':>15} {'max in periods':>15} {'op->landed p50 ms':>18} "
                  f"{'state KB':>9}")
            figures = []
            for stage in ("Loc-2", "Blob-2"):
                chain = scenario.chain(stage)
                period_wall_ms = chain.period_s / speed * 1e3
                downs = [e["downtime_ms"] for e in log if e["stage"] == stage]
                ops = [t * 1e3 for s, t in issued if s == stage]
                state_kb = len(make_component(chain.stages[0].component, chain.source, 0).export_state()) / 1024
                p50 = statistics.median(downs)
                print(f"{stage:7} {len(downs):>6} {period_wall_ms:>10.1f} {sinks0[stage]['latency_ms_p50']:>22.2f} "
                      f"{p50:>16.2f} {max(downs):>7.2f} {p50 / period_wall_ms:>15.3f} "
                      f"{max(downs) / period_wall_ms:>15.3f} {statistics.median(ops):>18.1f} {state_kb:>9.1f}")
                g, note = f"migration at x{speed:g}", f"the chain's period in wall time at x{speed:g}"
                figures += [
                    results.figure(f"{stage}: downtime p50 ({len(downs)} moves)", p50, "ms", "its period",
                                   period_wall_ms, group=g, note=note),
                    results.figure(f"{stage}: downtime, worst", max(downs), "ms", "its period", period_wall_ms,
                                   group=g, note=note),
                    results.figure(f"{stage}: command to landed, p50", statistics.median(ops), "ms", "its period",
                                   period_wall_ms, group=g, note=note),
                ]
            print(f"source periods missed during the {len(log)} migrations: {missed} (sources never stop; inputs "
                  f"that arrive during a move are held and run on the new host)")
            dups = sum(s["duplicates_total"] for s in {**end["basestation"]["sinks"], **{
                c: s for r in end["robots"].values() for c, s in r["status"]["sinks"].items()}}.values())
            print(f"duplicated outputs: {dups}")
            outputs = sum(s["received_total"] for s in {**end["basestation"]["sinks"], **{
                c: s for r in end["robots"].values() for c, s in r["status"]["sinks"].items()}}.values())
            figures += [
                results.figure(f"source periods missed during {len(log)} migrations", missed, "periods",
                               "migrations", len(log), group=g, note="the moves made"),
                results.figure("duplicated outputs", dups, "outputs", "outputs received", outputs, group=g,
                               note="every output the sinks received in the run"),
            ]
            return figures


def main() -> None:
    json_out = results.pop_json_out()
    which = sys.argv[1:] or ["overhead", "migration"]  # hop: bench_relay.py runs on its own in `./run bench`
    figures = []
    for name in which:
        figures += {"overhead": bench_overhead, "hop": bench_hop, "migration": bench_migration}[name]()
    results.write_result("runtime", {"parts": which}, figures, json_out,
                         what="Agent overhead per run and migration downtime, each beside a baseline of the same run.")


if __name__ == "__main__":
    main()
