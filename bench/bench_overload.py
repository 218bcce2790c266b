"""Does a receiver whose main thread computes without pause hold its links up? (issue 17, item 4)

    .venv/bin/python bench/bench_overload.py [--seconds 8] [--rate 4000]

A receiver process subscribes to a data key through `ZenohBus` (the 8-sample channel and the
pump thread every node uses) while its main thread is either idle (the baseline, in the same
run) or computing in Python all the time, as an overloaded node's event loop does; a sender
process puts 230 KB frames reliably (BLOCK) at up to ``--rate`` a second. Printed for both: the
frames the receiver took per second, the sender's longest put (a put blocked past the lease,
1 s, makes Zenoh close the transport), and whether the receiver saw the sender's liveliness
token go (a closed transport). Not a test: ~2 × ``--seconds`` of two busy processes.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import results

from autopower.launch.localhost import endpoint, free_ports
from autopower.runtime.bus import ZenohBus, ZenohSettings

FRAME_BYTES = 230_000


def receiver(at: str, busy: bool, seconds: float) -> None:
    got = [0]
    lost = []
    with ZenohBus(ZenohSettings(listen=(at,))) as bus:
        bus.subscribe("bench/data", lambda _k, _p: got.__setitem__(0, got[0] + 1))
        bus.watch_liveliness("bench/alive/*", lambda _k, alive: None if alive else lost.append(time.monotonic()))
        print("ready", flush=True)
        while not got[0]:
            time.sleep(0.01)
        t0, n0 = time.monotonic(), got[0]
        until = t0 + seconds
        while time.monotonic() < until:
            if busy:  # an event loop that never waits: the pump gets the GIL only at switch intervals
                x = 0
                for i in range(20_000):
                    x += i
            else:
                time.sleep(0.05)
        taken = (got[0] - n0) / (time.monotonic() - t0)
        # within the window only: Zenoh reports the sender's token once as gone right as it connects
        print(json.dumps({"frames_per_s": taken, "transport_lost": any(t0 <= t < until for t in lost)}), flush=True)


def sender(at: str, rate: float, seconds: float) -> None:
    with ZenohBus(ZenohSettings(connect=(at,), shared_memory=False)) as bus:
        bus.declare_token("bench/alive/sender")
        time.sleep(1.0)
        frame = bytes(FRAME_BYTES)
        t0, n, worst = time.monotonic(), 0, 0.0
        while time.monotonic() - t0 < seconds + 2.0:  # past the receiver's window, which starts later
            due = t0 + n / rate
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            a = time.monotonic()
            bus.publish("bench/data", frame)
            worst = max(worst, time.monotonic() - a)
            n += 1
        print(json.dumps({"sent_per_s": n / (time.monotonic() - t0), "worst_put_ms": worst * 1000}), flush=True)


def run(busy: bool, rate: float, seconds: float) -> dict:
    at = endpoint(free_ports(1)[0])
    me = [sys.executable, __file__]
    rx = subprocess.Popen(me + ["--role", "rx", "--at", at, "--seconds", str(seconds)] + (["--busy"] if busy else []),
                          stdout=subprocess.PIPE, text=True)
    assert rx.stdout.readline().strip() == "ready"
    tx = subprocess.Popen(me + ["--role", "tx", "--at", at, "--rate", str(rate), "--seconds", str(seconds)],
                          stdout=subprocess.PIPE, text=True)
    out = {**json.loads(rx.stdout.readline()), **json.loads(tx.stdout.readline())}
    rx.wait(30)
    tx.wait(30)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rate", type=float, default=4000.0, help="frames a second the sender tries to put")
    ap.add_argument("--role", choices=("rx", "tx"), help=argparse.SUPPRESS)
    ap.add_argument("--at", help=argparse.SUPPRESS)
    ap.add_argument("--busy", action="store_true", help=argparse.SUPPRESS)
    results.add_json_out(ap)
    args = ap.parse_args()
    if args.role == "rx":
        return receiver(args.at, args.busy, args.seconds)
    if args.role == "tx":
        return sender(args.at, args.rate, args.seconds)
    print(f"== 230 KB frames, reliable, up to {args.rate:g}/s for {args.seconds:g} s; load average "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores ==")
    idle = run(False, args.rate, args.seconds)
    busy = run(True, args.rate, args.seconds)
    for name, r in (("receiver idle (baseline)", idle), ("receiver's main thread busy", busy)):
        print(f"{name:30s} took {r['frames_per_s']:7.0f} frames/s (sender put {r['sent_per_s']:6.0f}/s), "
              f"longest put {r['worst_put_ms']:6.1f} ms, transport lost: {r['transport_lost']}")
    print(f"busy / idle: {busy['frames_per_s'] / idle['frames_per_s']:.2f}x the frames taken; the whole-mission "
          f"base station gets ~440 camera frames/s at x55")
    note = "the same receiver with its main thread idle, same sender, same run"
    figures = [
        results.figure("frames taken per second, main thread busy", busy["frames_per_s"], "frames/s",
                       "main thread idle", idle["frames_per_s"], note=note),
        results.figure("sender's longest put, receiver busy", busy["worst_put_ms"], "ms", "main thread idle",
                       idle["worst_put_ms"], note=note),
        results.figure("transport lost while busy (1 = yes)", int(busy["transport_lost"]), "", "main thread idle",
                       int(idle["transport_lost"]), note=note),
    ]
    results.write_result("overload", {"seconds": args.seconds, "rate": args.rate}, figures, args.json_out,
                         what="Does a receiver whose main thread computes without pause keep its links up?")


if __name__ == "__main__":
    main()
