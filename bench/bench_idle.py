"""CPU of processes with nothing to do: a base station waiting for robots, a whole team at rest.

    .venv/bin/python bench/bench_idle.py [--baseline DIR | PATH/TO/autopower] [--seconds S] [--variants]
                                         [--rounds N]

Not a timed test. CPU is read from /proc (each thread's time on a core from its schedstat, in
nanoseconds, finer than the user + system ticks) over S wall seconds and shown as a percentage
of one core:
- a lone base station waiting for its robots (no agent ever comes);
- a whole team under `up` (`up` itself with its link proxies and supervisor, the base station,
  three agents) running the default mission, then at rest (every chain disabled): per process,
  and split into the Python threads and Zenoh's own (its tokio runtimes: rx, tx, net, acc, ...).

--baseline measures another build the same way in the same run, alternating with this one:
a source checkout (``git worktree add /tmp/before main`` or ``git archive main autopower | tar
-x -C DIR``; it runs on this venv with PYTHONPATH=DIR), or the `autopower` command of another
venv (then only the waiting base station). --variants also measures this build's team at rest
without link proxies (``up --direct-links``) and with a 2 s Zenoh lease: where the rest goes.
--rounds N (with a source checkout as --baseline) then measures both teams at rest N more times
each, alternating, so that the load other work puts on the machine falls on both alike, and
prints the ratio of their medians.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results

from autopower.model.loading import load_scenario

AUTOPOWER = str(Path(sys.executable).parent / "autopower")
ZENOH_THREADS = ("rx-", "tx-", "net-", "acc-", "app-", "Watchdog")  # Zenoh's runtime threads (by name)


def threads(pid: int) -> dict[int, tuple[str, int]]:
    """tid -> (thread name, nanoseconds on a core so far)."""
    out = {}
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return out
    for task in tasks:
        try:
            name = (task / "comm").read_text().rstrip("\n")
            ran_ns = int((task / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue
        out[int(task.name)] = (name, ran_ns)
    return out


def cpu_ns(pids) -> int:
    return sum(t for pid in pids for _, t in threads(pid).values())


def tree(pid: int) -> list[int]:
    """`pid` and every descendant (children of children included)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            kids = []
        todo.extend(int(k) for k in kids)
    return out


def percent_of_core(pids_fn, seconds: float) -> float:
    before, t0 = cpu_ns(pids_fn()), time.monotonic()
    time.sleep(seconds)
    after, t1 = cpu_ns(pids_fn()), time.monotonic()
    return 100.0 * (after - before) / 1e9 / (t1 - t0)


def per_process(pids: dict[str, int], seconds: float) -> dict[str, tuple[float, float]]:
    """name -> (% of a core in all, % of it in Zenoh's threads), over ``seconds``."""
    before, t0 = {n: threads(p) for n, p in pids.items()}, time.monotonic()
    time.sleep(seconds)
    after, dt = {n: threads(p) for n, p in pids.items()}, time.monotonic() - t0
    out = {}
    for name, now in after.items():
        total = zenoh = 0
        for tid, (comm, ticks) in now.items():
            used = ticks - before[name].get(tid, (comm, 0))[1]  # a thread started meanwhile: all of it
            total += used
            zenoh += used if comm.startswith(ZENOH_THREADS) else 0
        out[name] = (100.0 * total / 1e9 / dt, 100.0 * zenoh / 1e9 / dt)
    return out


def build_env(baseline_src: str | None, base: dict) -> dict:
    env = dict(base)
    if baseline_src:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (baseline_src, os.environ.get("PYTHONPATH")) if p)
    return env


def waiting_basestation(command: str, seconds: float, src: str | None = None) -> float:
    proc = subprocess.Popen([command, "basestation", "--team", f"idle{os.getpid()}", "--listen", "tcp/127.0.0.1:0",
                             "--log-level", "error"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env=build_env(src, {**os.environ, "RERUN_ANALYTICS": "0"}), cwd=tempfile.gettempdir())
    try:
        time.sleep(8.0)  # past start-up (slower on a loaded machine)
        return percent_of_core(lambda: [proc.pid], seconds)
    finally:
        proc.terminate()
        proc.wait(15)


def team_status(name: str, env: dict) -> dict:
    """`autopower status --team NAME --json`'s snapshot ({} when it did not answer)."""
    out = subprocess.run([AUTOPOWER, "status", "--team", name, "--json", "--timeout", "3"], env=env,
                         capture_output=True, text=True, timeout=30)
    try:
        return json.loads(out.stdout) if out.returncode == 0 else {}
    except ValueError:
        return {}


def wait_ready(up: subprocess.Popen, name: str, env: dict, timeout_s: float = 90.0) -> dict:
    """The first snapshot of team NAME that says it is ready (exits if `up` ends or it takes too long)."""
    deadline = time.monotonic() + timeout_s
    while not (snap := team_status(name, env)).get("ready"):
        if time.monotonic() > deadline or up.poll() is not None:
            raise SystemExit("the team did not get ready")
        time.sleep(1.0)
    return snap


def team(seconds: float, src: str | None = None, extra: tuple[str, ...] = (), running: bool = True) -> dict:
    """{"running": per_process, "rest": per_process} for a whole team under `up` (the default mission)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = build_env(src, {**os.environ, "AUTOPOWER_STATE_DIR": str(Path(tmp) / "state"), "RERUN_ANALYTICS": "0"})
        name = f"rest{os.getpid()}{int(time.monotonic() * 1000) % 100000}"
        up = subprocess.Popen([AUTOPOWER, "up", "--team", name, "--json", "--log-dir", str(Path(tmp) / "logs"),
                               *extra], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                              cwd=tmp)  # `python -m` puts the working directory first on the children's path
        try:
            snap = wait_ready(up, name, env)
            time.sleep(2.0)
            # the nodes by `up`'s session (node -> pid): the agents are forked from its fork server
            # and carry the server's command line, so /proc cannot tell them apart
            session = json.loads((Path(env["AUTOPOWER_STATE_DIR"]) / "teams" / name / "session.json").read_text())
            base = load_scenario(session["scenario"]).basestation
            children = {("base station" if node == base else node): int(pid)
                        for node, pid in session["children"].items()}
            named = set(children.values())
            others = [pid for pid in tree(up.pid)[1:] if pid not in named]  # the fork server, helpers
            pids = {"up": up.pid, **dict(sorted(children.items())),
                    **{f"other {i + 1}": pid for i, pid in enumerate(others)}}
            out = {}
            if running:
                out["running"] = per_process(pids, seconds)
            for chain in snap.get("running") or []:
                subprocess.run([AUTOPOWER, "chain", "disable", chain, "--team", name], env=env,
                               capture_output=True, timeout=30)
            time.sleep(4.0)  # the last frames drain, the statuses settle into their rest cadence
            out["rest"] = per_process(pids, seconds)
            return out
        finally:
            up.send_signal(signal.SIGTERM)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                up.kill()


def show(label: str, this: dict, before: dict | None) -> None:
    print(f"  {label}: % of one core, per process (of which Zenoh's threads)")
    names = list(this)
    for name in names + ["total"]:
        def cell(m):
            if m is None:
                return ""
            if name == "total":  # noqa: B023 (called in this iteration)
                return f"{sum(v[0] for v in m.values()):6.2f} ({sum(v[1] for v in m.values()):5.2f})"
            v = m.get(name)  # noqa: B023 (called in this iteration)
            return f"{v[0]:6.2f} ({v[1]:5.2f})" if v else ""
        row = f"    {name:13s} this build {cell(this):16s}"
        if before is not None:
            row += f"  before {cell(before):16s}"
        print(row)


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default=None, help="a source checkout of the build to compare with, "
                                                         "or its `autopower` command")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--variants", action="store_true", help="also at rest without proxies, and with a 2 s lease")
    parser.add_argument("--rounds", type=int, default=0, help="then both teams at rest N more times each, "
                                                               "alternating (needs a source checkout as --baseline)")
    results.add_json_out(parser)
    args = parser.parse_args()
    src = cmd = None
    if args.baseline:
        if Path(args.baseline).is_dir():
            src = str(Path(args.baseline).resolve())
        else:
            cmd = args.baseline
    print(f"CPU over {args.seconds:g} s wall, % of one core ({os.cpu_count()} cores; load average {load()})")
    waiting = waiting_basestation(AUTOPOWER, args.seconds)
    print(f"  base station waiting for robots (this build): {waiting:6.2f} %")
    waiting_before = None
    if src or cmd:
        waiting_before = waiting_basestation(cmd or AUTOPOWER, args.seconds, src)
        print(f"  base station waiting for robots (before):     {waiting_before:6.2f} %")
    before = team(args.seconds, src) if src else None
    this = team(args.seconds)
    show("whole team running the default mission (chains enabled)", this["running"],
         before and before["running"])
    show("the same team at rest (every chain disabled)", this["rest"], before and before["rest"])
    def total(m: dict) -> float:
        return sum(v[0] for v in m.values())

    def zenoh(m: dict) -> float:
        return sum(v[1] for v in m.values())

    rest, running = this["rest"], this["running"]
    g = f"% of one core over {args.seconds:g} s"
    figures = [
        results.figure("whole team at rest (every chain disabled)", total(rest), "% of a core",
                       "the same team running", total(running), group=g,
                       note="the same team running the default mission just before, all processes"),
        results.figure("whole team at rest: Zenoh's own threads", zenoh(rest), "% of a core", "the team at rest",
                       total(rest), group=g, note="all the team's threads at rest"),
        results.figure("base station waiting for robots", waiting, "% of a core", "base station at rest",
                       rest.get("base station", (None,))[0], group=g,
                       note="the base station of the team at rest (its robots present, every chain disabled)"),
    ]
    for name, (pct, _z) in rest.items():
        if name in running:
            figures.append(results.figure(f"{name} at rest", pct, "% of a core", "running", running[name][0],
                                          group="per process", note="the same process running the mission"))
    if before is not None:
        figures.append(results.figure("whole team at rest", total(rest), "% of a core", "code before",
                                      total(before["rest"]), group="against the code before",
                                      note=f"the same on --baseline {args.baseline}"))
    if waiting_before is not None:
        figures.append(results.figure("base station waiting for robots", waiting, "% of a core", "code before",
                                      waiting_before, group="against the code before",
                                      note=f"the same on --baseline {args.baseline}"))
    if args.variants:
        direct = team(args.seconds, extra=("--direct-links",), running=False)["rest"]
        lease = team(args.seconds, extra=("--lease-ms", "2000"), running=False)["rest"]
        print("  this build at rest, where the rest goes (% of one core in all, of which Zenoh's threads):")
        for label, m in (("up --direct-links (no link proxies)", direct), ("up --lease-ms 2000 (keep-alives 4x rarer)", lease)):
            print(f"    {label:44s} {sum(v[0] for v in m.values()):6.2f} ({sum(v[1] for v in m.values()):5.2f})")
            figures.append(results.figure(f"team at rest, {label}", total(m), "% of a core", "the team at rest",
                                          total(rest), group="where the rest goes",
                                          note="this build's team at rest as `up` starts it"))
    if src and args.rounds > 0:
        rest: dict[str, list[float]] = {"before": [], "this build": []}
        print(f"  both teams at rest, alternating {args.rounds} times (% of one core in all; load average):")
        for _ in range(args.rounds):
            for label, where in (("before", src), ("this build", None)):
                rest[label].append(total(team(args.seconds, where, running=False)["rest"]))
                print(f"    {label:10s} {rest[label][-1]:6.2f}   ({load()})")
        medians = {k: statistics.median(v) for k, v in rest.items()}
        print(f"  medians: this build {medians['this build']:.2f} %, before {medians['before']:.2f} %; "
              f"ratio {medians['this build'] / medians['before']:.2f}")
    print(f"  load average after: {load()}")
    results.write_result("idle", {"seconds": args.seconds, "variants": args.variants, "rounds": args.rounds,
                                  "baseline": args.baseline}, figures, args.json_out, what=__doc__.splitlines()[0],
                         extra={"rest": rest, "running": running})


if __name__ == "__main__":
    main()
