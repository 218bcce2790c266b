"""What Zenoh alone costs a team at rest: the floor under issue 17's "team at rest <= 2 % of a core".

    .venv/bin/python bench/bench_zenoh_floor.py [--seconds 20] [--team] [--json]

Not a timed test. Five processes that do nothing but hold a Zenoh session (`runtime.bus.ZenohBus`)
are linked as a team under `up` is: the base station and three robots, one link per pair (the
later node connects to the earlier one), and the operator's session to the base station. Each
link is what the team's links are: mutual TLS against a team CA made for this run, the lease
the team detects a cut link with (`up`'s and the demo's 0.5 s) and `up`'s 2 keep-alives per
lease. No subscription, no status, no Python loop, no link proxy: what these processes spend is
Zenoh keeping its links alive, which no code above it can take away. Their CPU is read from each
thread's schedstat over ``--seconds``, as `bench_idle.py` reads the team's.

Printed beside it, in the same run: the same five sessions with a 2 s lease (4 times fewer
keep-alives, and cut links found 4 times later), over plain tcp (no TLS), and without shared
memory (which the team's frames need between local processes; a link that can use it wakes
Zenoh's net thread 20 times a second, measured on zenoh 1.10.2, whatever the lease). With ``--team`` the
whole team at rest is measured too (`bench_idle.team`, every chain disabled), and the floor's
share of it is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_idle, beside this file
from bench_idle import cpu_ns, load  # noqa: E402

NODES = ("laptop", "r1", "r2", "r3")
OPERATOR = "operator"

# A child holds one session until its stdin closes (the bench ended, or died: no orphan is left).
CHILD = """
import json, sys
from autopower.runtime.bus import TlsFiles, ZenohBus, ZenohSettings
cfg = json.loads(sys.argv[1])
tls = TlsFiles(**cfg["tls"]) if cfg["tls"] else None
bus = ZenohBus(ZenohSettings(listen=tuple(cfg["listen"]), connect=tuple(cfg["connect"]), lease_ms=cfg["lease_ms"],
                             keep_alive=cfg["keep_alive"], tls=tls, shared_memory=cfg["shared_memory"]))
print(json.dumps({"ready": True}), flush=True)
sys.stdin.read()
bus.close()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def links_up(pids: dict[str, int], expected: dict[str, int], timeout_s: float = 15.0) -> bool:
    """Every process has its links (established TCP connections of its own, counted from /proc)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if all(established(pid) >= expected[name] for name, pid in pids.items()):
            return True
        time.sleep(0.2)
    return False


def established(pid: int) -> int:
    """TCP connections of ``pid`` in state ESTABLISHED (its sockets' inodes matched in /proc/net/tcp)."""
    inodes = set()
    try:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            try:
                target = os.readlink(fd)
            except OSError:
                continue
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    except OSError:
        return 0
    count = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 9 and fields[3] == "01" and fields[9] in inodes:
                count += 1
    return count


def sessions(seconds: float, lease_ms: int, keep_alive: int, tls: bool, workdir: Path,
             shared_memory: bool = True) -> dict:
    """The five idle sessions, linked as a team is; CPU per process over ``seconds``.

    The nodes keep Zenoh's shared memory on, as the team's do (their frames cross it), unless
    ``shared_memory`` is False; the operator's session never has it, as `up`'s has not.
    """
    names = [*NODES, OPERATOR]
    identities = None
    if tls:
        from autopower.launch.identities import LocalIdentities

        identities = LocalIdentities.create("floor", NODES, workdir / f"tls-{lease_ms}")
    scheme = "tls" if tls else "tcp"
    ports = {n: free_port() for n in NODES}
    connect = {n: [f"{scheme}/127.0.0.1:{ports[p]}" for p in NODES[:i]] for i, n in enumerate(NODES)}
    connect[OPERATOR] = [f"{scheme}/127.0.0.1:{ports[NODES[0]]}"]
    expected = {n: len(NODES) - 1 for n in NODES}
    expected[NODES[0]] += 1  # the operator's link
    expected[OPERATOR] = 1
    procs: dict[str, subprocess.Popen] = {}
    try:
        for name in names:
            files = identities.files(name) if identities else None
            cfg = {"listen": [f"{scheme}/127.0.0.1:{ports[name]}"] if name in ports else [],
                   "connect": connect[name], "lease_ms": lease_ms, "keep_alive": keep_alive,
                   "shared_memory": None if shared_memory and name != OPERATOR else False,
                   "tls": {"ca": files.ca, "cert": files.cert, "key": files.key} if files else None}
            procs[name] = subprocess.Popen([sys.executable, "-c", CHILD, json.dumps(cfg)], stdin=subprocess.PIPE,
                                           stdout=subprocess.PIPE, text=True)
            if procs[name].stdout.readline().strip() != '{"ready": true}':
                raise SystemExit(f"the {name} session did not start (its stderr is above)")
        pids = {n: p.pid for n, p in procs.items()}
        if not links_up(pids, expected):
            got = {n: established(pid) for n, pid in pids.items()}
            raise SystemExit(f"the sessions did not link up within 15 s: {got} established, {expected} expected")
        time.sleep(1.0)  # the links' first exchanges over
        before = {n: cpu_ns([pid]) for n, pid in pids.items()}
        t0 = time.monotonic()
        time.sleep(seconds)
        wall = time.monotonic() - t0
        per = {n: (cpu_ns([pid]) - before[n]) / 1e9 / wall * 100.0 for n, pid in pids.items()}
        alive = all(p.poll() is None for p in procs.values())
        links = {n: established(pid) for n, pid in pids.items()}
        return {"lease_ms": lease_ms, "keep_alive": keep_alive, "tls": tls, "shared_memory": shared_memory,
                "total_pct": sum(per.values()),
                "per_process_pct": per, "links_at_end": links, "all_alive": alive,
                "links_kept": all(links[n] >= expected[n] for n in names)}
    finally:
        for p in procs.values():
            try:
                p.stdin.close()
            except OSError:
                pass
        for p in procs.values():
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if identities is not None:
            identities.remove()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--team", action="store_true", help="also the whole team at rest (bench_idle), same run")
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout, nothing else")
    results.add_json_out(parser)
    args = parser.parse_args()
    out: dict = {"load_start": load()}
    with tempfile.TemporaryDirectory(prefix="zenoh-floor-") as tmp:
        work = Path(tmp)
        out["floor"] = sessions(args.seconds, 500, 2, True, work)
        out["lease_2s"] = sessions(args.seconds, 2000, 2, True, work)
        out["plain_tcp"] = sessions(args.seconds, 500, 2, False, work)
        out["no_shared_memory"] = sessions(args.seconds, 500, 2, True, work, shared_memory=False)
    if args.team:
        from bench_idle import team

        rest = team(args.seconds, running=False)["rest"]  # name -> (% of a core, of which Zenoh's threads)
        out["team_at_rest_pct"] = sum(v[0] for v in rest.values())
        out["team_at_rest_zenoh_threads_pct"] = sum(v[1] for v in rest.values())
        out["floor_share_of_team"] = out["floor"]["total_pct"] / out["team_at_rest_pct"]
    out["load_end"] = load()
    floor = out["floor"]["total_pct"]
    note = ("five processes holding only Zenoh sessions, linked as a team is: mutual TLS, 0.5 s lease, "
            "2 keep-alives per lease, shared memory on")
    figures = [results.figure(f"five sessions, {label}", out[key]["total_pct"], "% of a core", "the team's links",
                              floor, note=note)
               for key, label in (("lease_2s", "TLS, 2 s lease"), ("plain_tcp", "plain tcp, 0.5 s lease"),
                                  ("no_shared_memory", "TLS, 0.5 s lease, no shared memory"))]
    if args.team:
        figures.insert(0, results.figure("whole team at rest (bench_idle, every chain disabled)",
                                         out["team_at_rest_pct"], "% of a core", "the team's links", floor,
                                         note=note))
    else:
        figures.insert(0, results.figure("five sessions, the team's links", floor, "% of a core",
                                         "the team's links", floor, note=note))
    results.write_result("zenoh_floor", {"seconds": args.seconds, "team": args.team}, figures, args.json_out,
                         what="What Zenoh alone costs a team at rest: the floor under the team's own CPU at rest.",
                         extra=out)
    if args.json:
        print(json.dumps(out))
        return
    print(f"load average at the start: {out['load_start']}")
    for key, label in (("floor", "TLS, 0.5 s lease, 2 keep-alives (the team's links)"),
                       ("lease_2s", "TLS, 2 s lease"), ("plain_tcp", "plain tcp, 0.5 s lease"),
                       ("no_shared_memory", "TLS, 0.5 s lease, no shared memory")):
        r = out[key]
        per = ", ".join(f"{n} {v:.2f}" for n, v in r["per_process_pct"].items())
        kept = "links kept" if r["links_kept"] and r["all_alive"] else f"LINKS LOST: {r['links_at_end']}"
        print(f"Zenoh sessions alone, {label}: {r['total_pct']:.2f} % of a core ({per}; {kept})")
    print(f"2 s lease / 0.5 s: {out['lease_2s']['total_pct'] / out['floor']['total_pct']:.2f}; "
          f"plain tcp / TLS: {out['plain_tcp']['total_pct'] / out['floor']['total_pct']:.2f}; "
          f"no shared memory / with: {out['no_shared_memory']['total_pct'] / out['floor']['total_pct']:.2f}")
    if args.team:
        print(f"the whole team at rest (bench_idle, every chain disabled): {out['team_at_rest_pct']:.2f} % of a core "
              f"({out['team_at_rest_zenoh_threads_pct']:.2f} in Zenoh's threads); "
              f"the Zenoh floor is {out['floor_share_of_team']:.0%} of it")
    print(f"load average at the end: {out['load_end']}")


if __name__ == "__main__":
    main()
