"""Rerun logging overhead per status message, against baselines measured in the same run.

Three loops publish the same N `NodeStatus` messages (encoded each time, as an agent does)
through an `InMemoryBus`:

- ``bare``: no recorder;
- ``noop``: through the `RecordingBus` tap with a telemetry that does nothing (decode + dispatch);
- ``rerun``: through the tap with a real `Telemetry` writing an .rrd file (batched with
  ``send_columns``, flushed every second and at the end; the final flush and close are timed).

Prints µs/message of each, the ratio rerun/noop and rerun/bare, and the recording's size.
``python bench/bench_recording.py [-n 20000] [--repeat 3]`` — not a timed test.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import results

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("RERUN_ANALYTICS", "0")

from autopower.protocol import Keys, NodeStatus, SinkStats, SourceStats, encode  # noqa: E402
from autopower.recording.recorder import Recorder  # noqa: E402
from autopower.recording.telemetry import Telemetry  # noqa: E402
from autopower.runtime.bus import InMemoryHub  # noqa: E402


class NoopTelemetry:
    rr = None
    errors = 0

    def __getattr__(self, name):
        return lambda *a, **k: None


def status(i: int) -> NodeStatus:
    parts = {"cpu_idle": 0.4, "cpu_busy": 0.5, "802.11a:send": 0.1, "802.11a:receive": 0.05,
             "802.11a:sleep": 0.3, "bluetooth:send": 0.01, "bluetooth:receive": 0.01, "bluetooth:sleep": 0.02}
    return NodeStatus(
        node="r1", t_virtual=i * 5.0, t_unix=time.time(), plan_epoch=3, initial_j=64000.0,
        battery_j=64000.0 - i * 6.7, energy_j={k: v * i for k, v in parts.items()}, power_w=parts,
        cpu_utilisation=0.3, hosted={"Loc-1": "running", "Blob-2": "running"},
        sources={"Loc-1": SourceStats(run=0, produced=i, missed=0, produced_total=i)},
        sinks={"Loc-1": SinkStats(run=0, received=i, duplicates=0, contiguous=i, max_seq=i - 1, stale=0,
                                  latency_ms_p50=2.0, latency_ms_max=9.0, received_total=i, duplicates_total=0,
                                  digest=12345)},
        links={"laptop": True, "r2": True, "r3": i % 50 != 0}, runs={"Loc-1": i}, compute_ms={"Loc-1": 1.2},
        queue_depth=0, errors={}, counters={"forwarded": i}, depleted=False)


def run(kind: str, n: int, folder: Path) -> tuple[float, int]:
    hub = InMemoryHub()
    keys = Keys("bench")
    inner = hub.bus("r1")
    hub.bus("laptop").subscribe(keys.status_all, lambda k, p: None)
    recorder = None
    bus = inner
    if kind == "noop":
        recorder = Recorder(NoopTelemetry(), "r1")
        bus = recorder.tap(inner)
    elif kind == "rerun":
        recorder = Recorder(Telemetry(folder / f"bench-{time.monotonic_ns()}.rrd", kind="live"), "r1")
        bus = recorder.tap(inner)
    key = keys.status("r1")
    started = time.perf_counter()
    for i in range(n):
        bus.publish(key, encode(status(i)), reliable=False)
    if recorder is not None:
        recorder.close()
    elapsed = time.perf_counter() - started
    size = 0
    if kind == "rerun":
        size = sum(p.stat().st_size for p in folder.glob("bench-*.rrd"))
        for p in folder.glob("bench-*.rrd"):
            p.unlink()
    return elapsed, size


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", type=int, default=20_000)
    ap.add_argument("--repeat", type=int, default=3)
    results.add_json_out(ap)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        run("rerun", 200, folder)  # warm up: import rerun, open the first stream
        best = {k: float("inf") for k in ("bare", "noop", "rerun")}
        size = 0
        for _ in range(args.repeat):
            for kind in best:
                t, s = run(kind, args.n, folder)
                best[kind] = min(best[kind], t)
                size = s or size
    us = {k: v / args.n * 1e6 for k, v in best.items()}
    print(f"{args.n} status messages, best of {args.repeat}:")
    for k in best:
        print(f"  {k:<6} {us[k]:8.2f} µs/message")
    print(f"  recording overhead (rerun - bare): {us['rerun'] - us['bare']:.2f} µs/message; "
          f"of which Rerun itself (rerun - noop): {us['rerun'] - us['noop']:.2f} µs/message")
    print(f"  ratio rerun/noop {best['rerun'] / best['noop']:.2f}x, rerun/bare {best['rerun'] / best['bare']:.2f}x")
    print(f"  recording size {size / args.n:.0f} B/message")
    figures = [
        results.figure("publish with the Rerun recorder", us["rerun"], "us/message", "bare publish", us["bare"],
                       note="the same messages published with no recorder"),
        results.figure("publish with the Rerun recorder", us["rerun"], "us/message", "no-op recorder", us["noop"],
                       note="the recorder's tap with a telemetry that does nothing (decode and dispatch only)"),
        results.figure("publish through the no-op recorder", us["noop"], "us/message", "bare publish", us["bare"],
                       note="the same messages published with no recorder"),
        results.figure("recording size", size / args.n, "B/message", "encoded status", len(encode(status(1))),
                       note="one status message as published"),
    ]
    results.write_result("recording", {"n": args.n, "repeat": args.repeat}, figures, args.json_out,
                         what="Rerun logging overhead per status message, against baselines measured in the same run.")


if __name__ == "__main__":
    main()
