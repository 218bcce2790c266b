"""An agent's memory under a flood of garbage: resident memory at rest, at the peak, after.

    .venv/bin/python bench/bench_flood.py [--messages N] [--mb M] [--baseline PATH/TO/autopower]

Not a timed test. A real `autopower agent` process listens on 127.0.0.1; this process joins
it over Zenoh and publishes N messages of M MB of random bytes as fast as Zenoh takes them,
half on the agent's data key (bulk) and half on its control key (urgent). The agent can only
decode and drop them. Its resident memory at rest (before the flood) is the baseline: the
peak and the memory 3 s after the flood are printed as ratios against it. With --baseline,
the same flood is sent to another build's agent (e.g. one without bounded queues) in the
same run, so the two are measured on the same machine under the same load.
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def flood(command: str, messages: int, size_mb: float, team: str) -> tuple[float, float, float, float]:
    """(rest MB, peak MB, after MB, seconds the flood took) of one agent built by `command`."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = tempfile.TemporaryFile()
    agent = subprocess.Popen([command, "agent", "--robot", "r1", "--team", team, "--listen", endpoint,
                              "--log-level", "error"], stdout=log, stderr=log,
                             env={**os.environ, "RERUN_ANALYTICS": "0"})
    try:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        session = zenoh.open(cfg)
        try:
            alive = session.liveliness().get(f"autopower/{team}/alive/r1", timeout=1.0)
            deadline = time.monotonic() + 30
            while not list(alive):
                if time.monotonic() > deadline or agent.poll() is not None:
                    raise SystemExit("the agent did not come up")
                time.sleep(0.2)
                alive = session.liveliness().get(f"autopower/{team}/alive/r1", timeout=1.0)
            time.sleep(1.0)
            rest = rss_mb(agent.pid)
            peak = rest
            done = threading.Event()

            def sample():
                nonlocal peak
                while not done.is_set():
                    peak = max(peak, rss_mb(agent.pid))
                    time.sleep(0.05)

            sampler = threading.Thread(target=sample, daemon=True)
            sampler.start()
            garbage = os.urandom(int(size_mb * 2**20))
            keys = [f"autopower/{team}/node/r1/data", f"autopower/{team}/node/r1/control"]
            publishers = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                          for k in keys]
            started = time.monotonic()
            for i in range(messages):
                publishers[i % 2].put(garbage)
            took = time.monotonic() - started
            time.sleep(3.0)
            done.set()
            sampler.join()
            after = rss_mb(agent.pid)
            if agent.poll() is not None:
                raise SystemExit(f"the agent died under the flood (exit {agent.returncode})")
            return rest, peak, after, took
        finally:
            session.close()
    finally:
        agent.terminate()
        try:
            agent.wait(10)
        except subprocess.TimeoutExpired:
            agent.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, default=4000)
    parser.add_argument("--mb", type=float, default=1.0)
    parser.add_argument("--baseline", default=None, help="another build's autopower command to compare with")
    args = parser.parse_args()
    builds = [("this build", AUTOPOWER)] + ([("baseline", args.baseline)] if args.baseline else [])
    print(f"{args.messages} garbage messages of {args.mb:g} MB to one agent (half data, half control)")
    print(f"{'build':>11} {'rest MB':>8} {'peak MB':>8} {'after MB':>9} {'peak/rest':>10} {'after/rest':>11} {'flood s':>8}")
    for name, command in builds:
        rest, peak, after, took = flood(command, args.messages, args.mb, f"flood{os.getpid()}")
        print(f"{name:>11} {rest:>8.0f} {peak:>8.0f} {after:>9.0f} {peak / rest:>9.2f}x {after / rest:>10.2f}x {took:>8.1f}")


if __name__ == "__main__":
    main()
