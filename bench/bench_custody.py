"""What custody costs per frame, against encoding the same frame (measured in the same run).

    .venv/bin/python bench/bench_custody.py [--frames 20000]

Custody (`autopower.agent.custody`) keeps every frame a node produces until its consumer's
status acknowledges it. Per frame that is: stamp its floor, keep it, and drop it again when a
report covers it (reports come every 0.5 s, so each covers a batch). The baseline is what every
frame costs anyway: `encode` (msgpack) of the same frame. Not a test: prints figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from autopower.agent.custody import Custody, Report  # noqa: E402
from autopower.protocol import ChainFrame, Consumed, encode  # noqa: E402


def frames(n: int, size: int) -> list[ChainFrame]:
    payload = bytes(size)
    return [ChainFrame(chain="Blob-2", run=0, seq=i, target=1, t_virtual=0.0, t_unix=0.0, payload_len=size,
                       payload=payload) for i in range(n)]


def custody_cost(batch: list[ChainFrame], per_report: int) -> float:
    custody = Custody()
    started = time.perf_counter()
    for i, f in enumerate(batch):
        f = dataclasses.replace(f, floor=custody.floor(f.chain, f.target, f.run, f.seq))
        custody.keep(f, 0.0)
        if (i + 1) % per_report == 0:  # a status acknowledging everything so far
            c = Consumed(run=0, generation=1, next_seq=i + 1, max_seq=i, missing=())
            custody.on_report(f.chain, f.target, Report(node="laptop", t_unix=float(i), consumed=c))
            custody.due(float(i))
    elapsed = time.perf_counter() - started
    assert len(custody) < per_report
    return elapsed / len(batch)


def encode_cost(batch: list[ChainFrame]) -> float:
    started = time.perf_counter()
    for f in batch:
        encode(f)
    return (time.perf_counter() - started) / len(batch)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    args = parser.parse_args()
    if not 100 <= args.frames <= 1_000_000:
        raise SystemExit("--frames must be within 100..1000000")
    # a Blob output (200 B) at 4 Hz, a camera frame (230 kB): reports every 0.5 s cover 2 frames at
    # speed 1 and 20 at speed 10
    for label, size in (("blob result, 200 B", 200), ("camera frame, 230 kB", 230_415)):
        n = args.frames if size < 10_000 else max(100, args.frames // 20)
        batch = frames(n, size)
        base = min(encode_cost(batch) for _ in range(3))
        for per_report in (2, 20):
            cost = min(custody_cost(batch, per_report) for _ in range(3))
            print(f"{label:<22} report every {per_report:>2} frames: custody {cost * 1e6:6.2f} us/frame, "
                  f"encode {base * 1e6:6.2f} us/frame, ratio {cost / base:5.2f}x")


if __name__ == "__main__":
    main()
