"""CPU of the strict codec on what a live team exchanges, before vs after, in one run.

    .venv/bin/python bench/bench_codec.py [--baseline-tree DIR]

The messages a base station handles most at a high speed-up (the paper's mission, every stage on
it): camera frames (a `Packet` around a 230 kB `ChainFrame`; its body decoded again), laser
frames and their outputs (805 B), and the robots' statuses. Each is encoded and decoded strictly
(every field's type checked) as the processes do. Printed: microseconds of CPU per message (the
best of 5 rounds: the machine's load only ever adds), and with ``--baseline-tree DIR`` (a checkout
of the code before) the same measured in a child process on that code, in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import results


def messages() -> dict[str, tuple[object, object]]:
    """name -> (the message on the wire, the frame its body carries or None)"""
    from autopower.protocol import Ack, ChainFrame, Consumed, NodeStatus, Packet, SinkStats, SourceStats, encode

    def frame(chain: str, size: int, target: int) -> ChainFrame:
        return ChainFrame(chain=chain, run=0, seq=12345, target=target, t_virtual=617.25, t_unix=1.7e9 + 0.125,
                          payload_len=size, payload=os.urandom(size), floor=12300)

    def packet(f: ChainFrame) -> Packet:
        return Packet(path=("r2", "laptop"), media=("802.11a",), hop=1, charge_bytes=len(f.payload), weight=1.0,
                      purpose="chain", chain=f.chain, body=encode(f))

    chains = ("Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3")
    status = NodeStatus(
        node="r2", t_virtual=617.25, t_unix=1.7e9, plan_epoch=3, initial_j=64000.0, battery_j=61234.5,
        energy_j={k: 123.456 for k in ("cpu_idle", "cpu_busy", "802.11a:send", "802.11a:receive", "802.11a:idle")},
        power_w={k: 1.234 for k in ("cpu_idle", "cpu_busy", "802.11a:send", "802.11a:receive", "802.11a:idle")},
        cpu_utilisation=0.42, hosted={"Loc-2": "running"},
        sources={c: SourceStats(run=0, produced=12345, missed=0, produced_total=12345) for c in ("Loc-2", "Blob-2")},
        sinks={"Loc-2": SinkStats(run=0, received=1234, duplicates=0, contiguous=1234, max_seq=1233, stale=0,
                                  latency_ms_p50=12.5, latency_ms_max=80.25, received_total=1234, duplicates_total=0,
                                  digest=1234567890)},
        links={"laptop": True, "r1": True, "r3": True}, runs={"Loc-2": 1234}, compute_ms={"Loc-2": 2.5},
        queue_depth=0, errors={}, counters={"forwarded": 0, "late-captures": 12, "custody-frames": 210,
                                            "custody-bytes": 48_000_000, "custody-resent": 0},
        depleted=False, acks_wanted=tuple(f"{c}#1" for c in chains),
    )
    # the acknowledgement that goes with the status, to a producer of five hops (`Ack`)
    ack = Ack(node="r2", t_unix=1.7e9, queue_wait_s=0.0,
              consumed={f"{c}#1": Consumed(run=0, generation=1, next_seq=1234, max_seq=1240, missing=((1236, 1236),))
                        for c in chains})
    camera, laser, output = frame("Blob-2", 230415, 0), frame("Loc-2", 1059, 0), frame("Loc-2", 805, 1)
    return {"camera frame 230 kB": (packet(camera), camera), "laser frame 1 kB": (packet(laser), laser),
            "Loc output 805 B": (packet(output), output), "robot status": (status, None),
            "acknowledgement": (ack, None)}


def body_of(fields):
    """A packet's body in its wire fields: the last of them (protocol 3), or "body" (a baseline tree's 2)."""
    return fields["body"] if isinstance(fields, dict) else fields[-1]


def with_body(fields, body: bytes):
    return {**fields, "body": body} if isinstance(fields, dict) else [*fields[:-1], body]


def measure(rounds: int = 5) -> dict[str, dict[str, float]]:
    import msgpack

    from autopower.protocol import Packet, decode, encode

    def unpack(b: bytes):
        return msgpack.unpackb(b, raw=False, strict_map_key=False)

    out = {}
    for name, (msg, inner) in messages().items():
        data = encode(msg)
        n = max(200, int(2e6 // len(data)))
        wire = unpack(data)  # the baseline: bare msgpack of the same bytes, no field checked
        wire_inner = unpack(body_of(wire[3])) if inner is not None else None

        def decode_bare(n=n, data=data, inner=inner) -> None:  # this message's values, bound explicitly
            for _ in range(n):
                m = unpack(data)
                if inner is not None:
                    unpack(body_of(m[3]))

        def encode_bare(n=n, wire=wire, wire_inner=wire_inner) -> None:
            for _ in range(n):
                if wire_inner is not None:
                    msgpack.packb([*wire[:3], with_body(wire[3], msgpack.packb(wire_inner, use_bin_type=True))],
                                  use_bin_type=True)
                else:
                    msgpack.packb(wire, use_bin_type=True)

        def decode_all(n=n, data=data, msg=msg, inner=inner) -> None:  # this message's values, bound explicitly
            for _ in range(n):
                m = decode(data, type(msg))
                if inner is not None:
                    decode(m.body, type(inner))

        def encode_all(n=n, msg=msg, inner=inner) -> None:
            for _ in range(n):
                if inner is not None:  # as a sender does: the frame, then the packet around it
                    encode(Packet(path=msg.path, media=msg.media, hop=1, charge_bytes=msg.charge_bytes,
                                  weight=msg.weight, purpose=msg.purpose, chain=msg.chain, body=encode(inner)))
                else:
                    encode(msg)
        row = {}
        for what, fn in (("decode", decode_all), ("encode", encode_all), ("decode_msgpack", decode_bare),
                         ("encode_msgpack", encode_bare)):
            best = float("inf")
            for _ in range(rounds):
                t = time.process_time()
                fn()
                best = min(best, (time.process_time() - t) / n)
            row[what] = best * 1e6
        out[name] = row
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--baseline-tree", default=None, metavar="DIR")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    results.add_json_out(ap)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure()))
        return
    before = None
    if args.baseline_tree:
        env = {**os.environ, "PYTHONPATH": args.baseline_tree}
        before = json.loads(subprocess.run([sys.executable, __file__, "--child"], env=env, capture_output=True,
                                           text=True, check=True).stdout.strip().splitlines()[-1])
    after = measure()
    print(f"== strict codec, us of CPU per message (best of 5), load average {os.getloadavg()[0]:.2f} ==")
    print("(a frame is decoded as the base station does: its Packet, then the body; encoded the same way)")
    print(f"{'message':22} {'decode':>8} {'before':>8} {'ratio':>6}   {'encode':>8} {'before':>8} {'ratio':>6}")
    for name, row in after.items():
        b = (before or {}).get(name, {})
        cells = []
        for what in ("decode", "encode"):
            old = b.get(what)
            cells.append(f"{row[what]:>8.1f} {old if old is not None else float('nan'):>8.1f} "
                         f"{row[what] / old if old else float('nan'):>6.2f}")
        print(f"{name:22} {cells[0]}   {cells[1]}")
    print("bare msgpack of the same bytes (no field checked), us: " + "; ".join(
        f"{name} decode {row['decode_msgpack']:.1f}, encode {row['encode_msgpack']:.1f}" for name, row in after.items()))
    figures = []
    for name, row in after.items():
        for what in ("decode", "encode"):
            figures.append(results.figure(f"{what}, {name}", row[what], "us", "bare msgpack", row[f"{what}_msgpack"],
                                          note="msgpack of the same bytes with no field checked (CPU, best of 5)"))
            if before and before.get(name, {}).get(what):
                figures.append(results.figure(f"{what}, {name}", row[what], "us", "code before",
                                              before[name][what], group="against the code before",
                                              note=f"the same on --baseline-tree {args.baseline_tree}"))
    results.write_result("codec", {"baseline_tree": args.baseline_tree}, figures, args.json_out,
                         what="CPU of the strict codec per message a live team exchanges, against bare msgpack "
                              "on the same bytes.")


if __name__ == "__main__":
    main()
