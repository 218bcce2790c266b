"""What custody costs per frame, against encoding the same frame (measured in the same run).

    .venv/bin/python bench/bench_custody.py [--frames 20000]

Custody (`autopower.node.custody`) keeps every frame a node produces until its consumer's
status acknowledges it. Per frame that is: stamp its floor, keep it, and drop it again when a
report covers it (reports come every 0.5 s, so each covers a batch). The baseline is what every
frame costs anyway: `encode` (msgpack) of the same frame. Not a test: prints figures.

A *late* consumer is the hard case (x55 on this machine: the base station seconds behind): the hop
holds ``--late-held`` frames unacknowledged and each report covers the oldest batch only. With
``--baseline-tree DIR`` (a checkout of the code before) the same figures are measured on that
code in a child process, in the same run, and the ratios printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import results

from autopower.node.custody import Custody, Report
from autopower.protocol import ChainFrame, Consumed, encode


def frames(n: int, size: int) -> list[ChainFrame]:
    payload = bytes(size)
    return [ChainFrame(chain="Blob-2", run=0, seq=i, target=1, t_virtual=0.0, t_unix=0.0, payload_len=size,
                       payload=payload) for i in range(n)]


def custody_cost(batch: list[ChainFrame], per_report: int, behind: int = 0) -> float:
    """Per frame: floor, keep, and every ``per_report`` frames a report acknowledging all but the
    last ``behind`` frames (a consumer that far behind), then the resend check."""
    custody = Custody(max_frames_per_hop=behind + 2 * per_report + 10, max_bytes=1 << 40, max_age_s=1e9)
    started = time.perf_counter()
    for i, f in enumerate(batch):
        f = dataclasses.replace(f, floor=custody.floor(f.chain, f.target, f.run, f.seq))
        custody.keep(f, float(i))
        if (i + 1) % per_report == 0 and i + 1 > behind:  # a status acknowledging what reached the consumer
            c = Consumed(run=0, generation=1, next_seq=i + 1 - behind, max_seq=i - behind, missing=())
            custody.on_report(f.chain, f.target, Report(node="laptop", t_unix=float(i), consumed=c))
            custody.due(float(i))
    elapsed = time.perf_counter() - started
    assert len(custody) < per_report + behind
    return elapsed / len(batch)


def encode_cost(batch: list[ChainFrame]) -> float:
    started = time.perf_counter()
    for f in batch:
        encode(f)
    return (time.perf_counter() - started) / len(batch)


def measure(n_frames: int, late_held: int) -> dict[str, float]:
    out = {}
    # a Blob output (200 B) at 4 Hz, a camera frame (230 kB): reports every 0.5 s cover 2 frames at
    # speed 1 and 20 at speed 10; at x55 a camera robot sends 110 frames per 0.5 s
    for label, size in (("blob result, 200 B", 200), ("camera frame, 230 kB", 230_415)):
        n = n_frames if size < 10_000 else max(100, n_frames // 20)
        batch = frames(n, size)
        out[f"{label}: encode"] = min(encode_cost(batch) for _ in range(3))
        for per_report in (2, 20):
            out[f"{label}: report every {per_report} frames"] = min(custody_cost(batch, per_report) for _ in range(3))
    batch = frames(max(n_frames, 4 * late_held), 200)
    out[f"late consumer, {late_held} frames held, report every 110"] = min(
        custody_cost(batch, 110, behind=late_held) for _ in range(3))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--late-held", type=int, default=2_000, help="frames a late consumer leaves held")
    parser.add_argument("--baseline-tree", default=None, metavar="DIR")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)  # the baseline's run: JSON out
    results.add_json_out(parser)
    args = parser.parse_args()
    if not 100 <= args.frames <= 1_000_000 or not 0 <= args.late_held <= 100_000:
        raise SystemExit("--frames must be within 100..1000000, --late-held within 0..100000")
    before = None
    if args.baseline_tree:
        child = subprocess.run([sys.executable, __file__, "--frames", str(args.frames), "--late-held",
                                str(args.late_held), "--child"], capture_output=True, text=True, check=True,
                               env={**os.environ, "PYTHONPATH": str(Path(args.baseline_tree).resolve())})
        before = json.loads(child.stdout)
    now = measure(args.frames, args.late_held)
    if args.child:
        print(json.dumps(now))
        return
    for label, cost in now.items():
        line = f"{label:<62} {cost * 1e6:8.2f} us/frame"
        if not label.endswith("encode") and not label.startswith("late"):
            enc = now[label.split(":")[0] + ": encode"]
            line += f" ({cost / enc:5.2f}x encode)"
        if before is not None and label in before:
            line += f"; before {before[label] * 1e6:8.2f} us/frame, after/before {cost / before[label]:5.2f}"
        print(line)
    figures = []
    for label, cost in now.items():
        if label.endswith("encode"):
            continue
        kind = label.split(":")[0] if not label.startswith("late") else "blob result, 200 B"
        enc = now[kind + ": encode"]
        figures.append(results.figure(label, cost * 1e6, "us/frame", f"encode, {kind}", enc * 1e6,
                                      note="msgpack encode of the same frame, what every frame costs anyway"))
        if before is not None and label in before:
            figures.append(results.figure(label, cost * 1e6, "us/frame", "code before", before[label] * 1e6,
                                          group="against the code before",
                                          note=f"the same on --baseline-tree {args.baseline_tree}"))
    results.write_result("custody", {"frames": args.frames, "late_held": args.late_held,
                                     "baseline_tree": args.baseline_tree}, figures, args.json_out,
                         what=__doc__.splitlines()[0])


if __name__ == "__main__":
    main()
