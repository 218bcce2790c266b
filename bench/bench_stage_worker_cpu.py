"""What a blob finder run costs in a stage worker process against in the node's own process.

    .venv/bin/python bench/bench_stage_worker_cpu.py [--runs 400] [--json]

The same component (paper-fig7's blob finder, on the same 50 camera frames) runs ``--runs`` times
in this process and then in a stage worker (`autopower.node.workers`, forked from a zygote as a
node forks them; each frame handed over and its result collected, one at a time). Inside the
component's ``run`` it measures CPU (user + system), page faults; outside, the worker's whole CPU
per run (its scheduler count: the run plus receiving the frame and sending the result). The
worker is measured twice: with the environment a node gives its workers, and with glibc's malloc
left to its defaults (what the workers had before: each run's large temporaries were given back
to the kernel and faulted in again). Prints the ratios to in-process, measured in the same run,
and the machine's load average (a shared machine makes every figure noisy; compare within a run).
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import time

import results

FRAMES = 50


class Probe:
    """The blob finder, with the CPU (user, system) and minor page faults of each run appended to its output."""

    def __init__(self, robot: str, seed: int):
        from autopower.chains.blobfinder import BlobFinder

        self.finder = BlobFinder(robot)

    def run(self, payload: bytes) -> bytes:
        import resource

        r0 = resource.getrusage(resource.RUSAGE_SELF)
        out = self.finder.run(payload)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        return out + struct.pack("<ddd", r1.ru_utime - r0.ru_utime, r1.ru_stime - r0.ru_stime,
                                 r1.ru_minflt - r0.ru_minflt)


def _summary(samples: list[tuple[float, float, float]], whole_s: float | None, runs: int) -> dict:
    n = len(samples)
    return {"cpu_ms": sum(s[0] + s[1] for s in samples) / n * 1e3, "system_ms": sum(s[1] for s in samples) / n * 1e3,
            "faults": sum(s[2] for s in samples) / n,
            "process_cpu_ms": None if whole_s is None else whole_s / runs * 1e3}


def in_process(frames: list[bytes], runs: int) -> dict:
    probe = Probe("r2", 1)
    for frame in frames[:10]:
        probe.run(frame)  # warm, as a worker is below
    t0 = time.process_time()
    samples = [struct.unpack("<ddd", probe.run(frames[i % FRAMES])[-24:]) for i in range(runs)]
    return _summary(samples, time.process_time() - t0, runs)


def in_worker(frames: list[bytes], runs: int, malloc_defaults: bool) -> dict:
    from autopower.node import workers

    saved = dict(workers._MALLOC)
    if malloc_defaults:
        workers._MALLOC.clear()
    zygote = workers.Zygote()
    try:
        worker = workers.StageWorker(zygote, None)
        workers.WorkerComponent(worker, ["class", f"{Probe.__module__}:Probe", "r2", 1], timeout_s=60)
        for frame in frames[:10]:
            worker.submit(None, frame)
            while worker.poll(5.0) is None:
                pass
        cpu0, samples = worker.cpu_s(), []
        for i in range(runs):
            worker.submit(i, frames[i % FRAMES])
            done = None
            while done is None:
                done = worker.poll(5.0)
            samples.append(struct.unpack("<ddd", done[1][2][-24:]))
        return _summary(samples, worker.cpu_s() - cpu0, runs)
    finally:
        zygote.close()
        workers._MALLOC.update(saved)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=400)
    parser.add_argument("--json", action="store_true")
    results.add_json_out(parser)
    args = parser.parse_args()
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the worker imports Probe by name
    global Probe
    from bench_stage_worker_cpu import Probe  # noqa: F811 (importable, not __main__'s)

    from autopower.chains import make_source

    source = make_source("Blob", "r2", 1234)
    frames = [source.produce(i) for i in range(FRAMES)]
    load = [os.getloadavg()[0]]
    measured = {"in-process": in_process(frames, args.runs),
               "worker": in_worker(frames, args.runs, malloc_defaults=False),
               "worker, malloc defaults": in_worker(frames, args.runs, malloc_defaults=True)}
    load.append(os.getloadavg()[0])
    base = measured["in-process"]["cpu_ms"]
    note = "the same runs in this process (no worker), CPU per run inside the component's run"
    figures = []
    for name in ("worker", "worker, malloc defaults"):
        figures.append(results.figure(f"{name}: CPU per run", measured[name]["cpu_ms"], "ms", "in-process", base,
                                      note=note))
        figures.append(results.figure(f"{name}: page faults per run", measured[name]["faults"], "faults",
                                      "in-process", measured["in-process"]["faults"],
                                      note="minor page faults per run in this process"))
        if measured[name]["process_cpu_ms"] is not None:
            figures.append(results.figure(f"{name}: its process's CPU per run (hand-over included)",
                                          measured[name]["process_cpu_ms"], "ms", "in-process",
                                          measured["in-process"]["process_cpu_ms"],
                                          note="this process's CPU per run, the loop around the call included"))
    results.write_result("stage_worker_cpu", {"runs": args.runs}, figures, args.json_out,
                         what=__doc__.splitlines()[0])
    if args.json:
        print(json.dumps({"load_average": load, "results": measured}))
        return
    print(f"blob finder, {args.runs} runs each; load average {load[0]:.1f} -> {load[1]:.1f} on {os.cpu_count()} cores")
    for name, r in measured.items():
        whole = "" if r["process_cpu_ms"] is None else f", its process {r['process_cpu_ms']:.3f} ms/run"
        print(f"  {name:26s} run CPU {r['cpu_ms']:.3f} ms (system {r['system_ms']:.3f}), x{r['cpu_ms'] / base:.2f} "
              f"in-process; page faults {r['faults']:.0f}/run{whole}")


if __name__ == "__main__":
    main()
