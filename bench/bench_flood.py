"""An agent's memory under a flood of garbage: resident memory at rest, at the peak, after.

    .venv/bin/python bench/bench_flood.py [--messages N ...] [--mb M] [--baseline-ref REV | --baseline CMD]

Not a timed test. A real `autopower agent` process listens on 127.0.0.1; this process joins
it over Zenoh and publishes N messages of M MB of random bytes as fast as Zenoh takes them,
half on the agent's data key (bulk) and half on its control key (urgent). The agent can only
decode and drop them. Its resident memory at rest (before the flood) is the baseline: the
peak and the memory 3 s after the flood are printed as ratios against it. The same floods are
sent, in the same run, to the agent of another build: by default the commit before the bounded
subscriber channels (--baseline-ref, checked out with `git archive` into a temporary directory
and run on this environment), or any `autopower` command (--baseline). Several --messages
values show whether the peak grows with the flood's length (bounded: it does not). The agent's
"event queue full" warnings are counted: drops are logged once per interval, not per message.
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

import results
import zenoh

from autopower.errors import ProtocolError
from autopower.protocol import Keys, NodeStatus, StatusDelta, decode
from autopower.protocol.codec import message_kind
from autopower.protocol.statuses import KEY_EVERY_S, StatusAssembler

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float:
    kb = results.proc_status_kb(pid, "VmRSS")
    return kb / 1024 if kb is not None else float("nan")


ENVELOPE = b"\x94\xc4\x02AP"  # what every encoded message starts with: a 4-array, then the magic
BASELINE_REF = "414b935"  # the last commit whose subscribers used Zenoh's default 256-sample channel


def baseline_command(ref: str, into: str) -> tuple[list[str], dict[str, str]]:
    """An `autopower` command running the sources of git revision `ref` (extracted into `into`)."""
    repo = Path(__file__).resolve().parent.parent
    archive = subprocess.run(["git", "-C", str(repo), "archive", ref, "autopower"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", into], input=archive, check=True)
    # -P: not the current directory first (the bench runs from a checkout of this build)
    return ([sys.executable, "-P", "-c", "import sys; from autopower.cli.main import main; sys.exit(main())"],
            {"PYTHONPATH": into})


def flood(command: list[str], env: dict[str, str], messages: int, size_mb: float, team: str,
          prefix: bytes = b"", shared_memory: bool = False) -> dict:
    """Resident MB at rest, at the peak and 3 s after; how long the flood took; what the agent
    counted (its last status' errors) and how many drop warnings it logged."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    log = tempfile.TemporaryFile()
    agent = subprocess.Popen([*command, "agent", "--robot", "r1", "--team", team, "--listen", endpoint,
                              "--log-level", "warning"], stdout=log, stderr=log,
                             env={**os.environ, "RERUN_ANALYTICS": "0", **env})
    keys = Keys(team)
    try:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("connect/endpoints", f'["{endpoint}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        # by default the flood crosses the link as it would from another host; through shared
        # memory (Zenoh's default between two processes of one machine) it comes several times faster
        cfg.insert_json5("transport/shared_memory/enabled", "true" if shared_memory else "false")
        session = zenoh.open(cfg)
        statuses: list[bytes] = []
        try:
            session.declare_subscriber(keys.status("r1"), lambda s: statuses.append(s.payload.to_bytes()))
            alive = session.liveliness().get(keys.alive("r1"), timeout=1.0)
            deadline = time.monotonic() + 30
            while not list(alive):
                if time.monotonic() > deadline or agent.poll() is not None:
                    raise SystemExit("the agent did not come up")
                time.sleep(0.2)
                alive = session.liveliness().get(keys.alive("r1"), timeout=1.0)
            time.sleep(1.0)
            # a whole status first (`protocol.statuses`): the changes from it make the agent's last one whole
            deadline = time.monotonic() + KEY_EVERY_S + 5.0
            while not any(message_kind(p) == NodeStatus.KIND for p in list(statuses)) and time.monotonic() < deadline:
                time.sleep(0.2)
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
            garbage = prefix + os.urandom(int(size_mb * 2**20) - len(prefix))
            publishers = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                          for k in (keys.node_data("r1"), keys.node_control("r1"))]
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
            errors = last_errors(statuses)
            log.seek(0)
            text = log.read()
            return {"rest": rest, "peak": peak, "after": after, "took": took, "errors": errors,
                    "drop_logs": text.count(b"event queue full") + text.count(b"not an AutoPower message")}
        finally:
            session.close()
    finally:
        agent.terminate()
        try:
            agent.wait(10)
        except subprocess.TimeoutExpired:
            agent.kill()


def last_errors(statuses: list[bytes]) -> dict:
    """What the agent's last status counted. A baseline build of another protocol version sends a
    status this build's strict codec refuses: its counts are then unknown, not a failed bench."""
    if not statuses:
        return {}
    try:
        assembler, last = StatusAssembler(), None
        for payload in statuses:  # the last whole one, or the last change from one
            last = assembler.whole(decode(payload, (NodeStatus, StatusDelta))) or last
        return last.errors if last is not None else {}
    except ProtocolError:
        return {"(status of another protocol version: counts unknown)": 0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--messages", type=int, nargs="+", default=[4000, 16000])
    parser.add_argument("--mb", type=float, default=1.0)
    parser.add_argument("--baseline-ref", default=BASELINE_REF,
                        help="git revision of the build to compare with ('' for none)")
    parser.add_argument("--baseline", default=None, help="another build's autopower command instead")
    parser.add_argument("--enveloped", action="store_true",
                        help="garbage that starts like an AutoPower message (is queued, fails to decode)")
    parser.add_argument("--shared-memory", action="store_true",
                        help="flood through Zenoh's shared memory (a local attacker) instead of TCP")
    results.add_json_out(parser)
    args = parser.parse_args()
    figures = []
    with tempfile.TemporaryDirectory() as tmp:
        builds = [("this build", [AUTOPOWER], {})]
        if args.baseline:
            builds.append(("baseline", [args.baseline], {}))
        elif args.baseline_ref:
            builds.append((args.baseline_ref, *baseline_command(args.baseline_ref, tmp)))
        prefix = ENVELOPE if args.enveloped else b""
        print(f"{'enveloped ' if prefix else 'random '}garbage messages of {args.mb:g} MB to one agent "
              f"(half data, half control), over {'shared memory' if args.shared_memory else 'TCP'}")
        print(f"{'build':>11} {'messages':>9} {'rest MB':>8} {'peak MB':>8} {'after MB':>9} {'peak/rest':>10} "
              f"{'after/rest':>11} {'flood s':>8} {'drop logs':>10}  counted by the agent")
        for messages in args.messages:
            for name, command, env in builds:
                r = flood(command, env, messages, args.mb, f"flood{os.getpid()}", prefix,
                          args.shared_memory)
                counted = ", ".join(f"{k} {n}" for k, n in sorted(r["errors"].items())) or "-"
                print(f"{name:>11} {messages:>9} {r['rest']:>8.0f} {r['peak']:>8.0f} {r['after']:>9.0f} "
                      f"{r['peak'] / r['rest']:>9.2f}x {r['after'] / r['rest']:>10.2f}x {r['took']:>8.1f} "
                      f"{r['drop_logs']:>10}  {counted}", flush=True)
                g = f"{name}: {messages} messages of {args.mb:g} MB"
                note = "the agent's resident memory at rest, before the flood"
                figures += [
                    results.figure("resident memory at the peak", r["peak"], "MB", "at rest", r["rest"], group=g,
                                   note=note, detail=f"flood took {r['took']:.1f} s"),
                    results.figure("resident memory 3 s after", r["after"], "MB", "at rest", r["rest"], group=g,
                                   note=note, detail=f"{r['drop_logs']} drop warnings logged"),
                ]
    results.write_result("flood", {"messages": args.messages, "mb": args.mb, "baseline_ref": args.baseline_ref,
                                   "baseline": args.baseline, "enveloped": args.enveloped,
                                   "shared_memory": args.shared_memory}, figures, args.json_out,
                         what=__doc__.splitlines()[0])


if __name__ == "__main__":
    main()
