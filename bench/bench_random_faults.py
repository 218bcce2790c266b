"""Random faults against a real team under `up`, then the replay's verdict. Not a timed test.

    .venv/bin/python bench/bench_random_faults.py [--seed 1] [--faults 20] [--speed 10] [--json]

`up` starts the paper's mission (three agents, the base station, every link through its proxy,
a recording). Then ``--faults`` faults, drawn with ``--seed``, go through the real command line
(`autopower fault ...`), 0.5 to 4 s apart: a cut of any link, every robot cut from the base
station at once, a heal, a crash (SIGKILL, `up` restarts it) of any node including the base
station, a freeze of 0.2-1.5 s (SIGSTOP, then SIGCONT), a radio change. Everything cut is healed
at the end, the team runs 15 s more, `up` is stopped and the recording replayed.

Printed: each fault with its exit status (and the refusal, if any), the replay's lost and
duplicated outputs (and, apart from them, how many results a node dropped beyond its hold budget),
the energy model's error, every invariant that failed, and every ERROR line or traceback in the
processes' logs. Bounded: one team, ``--faults`` faults, every wait has a deadline, and `up` is
stopped whatever happens.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results

AUTOPOWER = str(Path(sys.executable).parent / "autopower")
NODES = ("laptop", "r1", "r2", "r3")
ROBOTS = NODES[1:]
READY_S = 90.0
SETTLE_S = 15.0


class Team:
    def __init__(self, workdir: Path, speed: float, team: str, stage_workers: str = "auto"):
        self.workdir, self.team = workdir, team
        self.env = {**os.environ, "AUTOPOWER_STATE_DIR": str(workdir / "state"), "RERUN_ANALYTICS": "0"}
        self.up = subprocess.Popen([AUTOPOWER, "up", "--team", team, "--speed", f"{speed:g}",
                                    "--log-dir", str(workdir / "logs"), "--record-dir", str(workdir / "rec"),
                                    "--stage-workers", stage_workers],
                                   stdout=open(workdir / "up.out", "w"), stderr=open(workdir / "up.err", "w"),
                                   env=self.env, cwd=workdir)

    def cli(self, *args: str) -> subprocess.CompletedProcess:
        return subprocess.run([AUTOPOWER, *args, "--team", self.team], env=self.env, capture_output=True,
                              text=True, timeout=30)

    def status(self) -> dict:
        out = self.cli("status", "--json", "--timeout", "3")
        try:
            return json.loads(out.stdout) if out.returncode == 0 else {}
        except ValueError:
            return {}

    def wait_ready(self) -> None:
        deadline = time.monotonic() + READY_S
        while not self.status().get("ready"):
            if time.monotonic() > deadline or self.up.poll() is not None:
                raise SystemExit(f"the team did not get ready within {READY_S:g} s (logs in {self.workdir})")
            time.sleep(1.0)

    def stop(self) -> int | None:
        if self.up.poll() is None:
            self.up.send_signal(signal.SIGTERM)
            try:
                self.up.wait(60)
            except subprocess.TimeoutExpired:
                self.up.kill()
                self.up.wait()
        return self.up.returncode


def inject(team: Team, rng: random.Random, cut: set, log: list, t0: float) -> None:
    """One random fault through the command line; what was cut is remembered for the heal."""
    kind = rng.choice(["cut", "cut", "heal", "crash", "freeze", "radio", "cut-base"])
    if kind == "heal" and not cut:
        kind = "cut"
    if kind == "cut":
        a, b = rng.sample(NODES, 2)
        commands = [["fault", "cut", a, b]]
        cut.add(tuple(sorted((a, b))))
    elif kind == "cut-base":
        commands = [["fault", "cut", r, "laptop"] for r in ROBOTS]
        cut.update(tuple(sorted((r, "laptop"))) for r in ROBOTS)
    elif kind == "heal":
        a, b = rng.choice(sorted(cut))
        commands = [["fault", "heal", a, b]]
        cut.discard((a, b))
    elif kind == "crash":
        commands = [["fault", "crash", rng.choice(NODES)]]
    elif kind == "freeze":
        robot = rng.choice(ROBOTS)
        commands = [["fault", "freeze", robot], ["sleep", f"{rng.uniform(0.2, 1.5):.2f}"], ["fault", "thaw", robot]]
    else:
        commands = [["fault", "radio", rng.choice(ROBOTS), "--laptop", rng.choice(["802.11a", "gsm"]),
                     "--robot", rng.choice(["802.11a", "bluetooth"])]]
    for args in commands:
        if args[0] == "sleep":
            time.sleep(float(args[1]))
            continue
        done = team.cli(*args)
        refusal = done.stderr.strip().splitlines()[-1][:160] if done.returncode and done.stderr.strip() else ""
        log.append({"t_s": round(time.monotonic() - t0, 1), "fault": " ".join(args[1:]), "exit": done.returncode,
                    "refusal": refusal})


def log_errors(logs: Path) -> dict[str, int]:
    """ERROR lines and tracebacks in the processes' logs, counted by message (numbers folded)."""
    out: dict[str, int] = {}
    for path in sorted(logs.glob("*.log")):
        for line in path.read_text(errors="replace").splitlines():
            if " ERROR " in line or line.startswith("Traceback") or "Error:" in line[:40]:
                message = re.sub(r"\d+", "N", line.split(" ", 2)[-1])[:160]
                out[message] = out.get(message, 0) + 1
    return out


def write(args, result: dict) -> None:
    """The replay's verdict against what the run did: outputs lost or duplicated against outputs recorded,
    faults refused against faults sent, invariants failed against checked, energy metered against the model."""
    faults = result["faults"]
    g = f"seed {args.seed}, {args.faults} faults, x{args.speed:g}"
    figures = [results.figure("fault commands refused", sum(1 for f in faults if f["exit"]), "commands",
                              "fault commands sent", len(faults), group=g, note="every `autopower fault` command sent")]
    if "lost" in result:
        outputs = result["outputs_produced"]
        note = "every output the sources said they produced, per run (tails included)"
        figures += [
            results.figure("outputs lost", result["lost"], "outputs", "outputs produced", outputs, group=g, note=note),
            results.figure("outputs duplicated", result["duplicated"], "outputs", "outputs produced", outputs,
                           group=g, note=note),
            results.figure("outputs dropped beyond a hold budget", result["dropped_by_budget"],
                           "outputs", "outputs produced", outputs, group=g, note=note),
            results.figure("outputs that died with a crashed process", result["died_with_process"], "outputs",
                           "outputs produced", outputs, group=g, note=note),
            results.figure("outputs abandoned when their chain restarted", result["abandoned"], "outputs",
                           "outputs produced", outputs, group=g, note=note),
            results.figure("outputs in flight when the team stopped", result["in_flight"], "outputs",
                           "outputs produced", outputs, group=g, note=note),
            results.figure("invariants failed", len(result["failed_invariants"]), "invariants", "invariants checked",
                           result["invariants_checked"], group=g, note="every invariant the replay checks"),
            results.figure("team energy metered (steady state)", result["energy_metered_steady_j"], "J",
                           "the energy model", result["energy_model_j"], group=g,
                           note="the model's power integrated over the same run (migrations, recovery, backlogs, "
                                "the control plane and the runtime's CPU, reported apart, left out of the "
                                "metered side)"),
            results.figure("team energy metered outside reconfigurations", result["energy_metered_outside_j"], "J",
                           "the energy model outside them", result["energy_model_outside_j"], group=g,
                           note=f"the run less its reconfiguration windows ({result['reconfiguration_covered_s']:.0f} "
                                "mission s: two status periods from each change of a robot's model power and "
                                "each fault), overheads left out as above"),
        ]
    figures.append(results.figure("ERROR lines or tracebacks in the logs", sum(result["log_errors"].values()),
                                  "lines", "fault commands sent", len(faults), group=g,
                                  note="every `autopower fault` command sent"))
    results.write_result("random_faults", {"seed": args.seed, "faults": args.faults, "speed": args.speed}, figures,
                         args.json_out, what="Random faults against a real team under `up`, then the replay's verdict.",
                         extra={"faults": faults, "log_errors": result["log_errors"],
                                "failed_invariants": result.get("failed_invariants")})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--faults", type=int, default=20)
    parser.add_argument("--speed", type=float, default=10.0)
    parser.add_argument("--stage-workers", choices=("off", "on", "auto"), default="auto",
                        help="up's: each stage's component in a worker process of its own (on), or in the node's")
    parser.add_argument("--json", action="store_true", help="one JSON object on stdout, nothing else")
    results.add_json_out(parser)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    workdir = Path(tempfile.mkdtemp(prefix=f"random-faults-{args.seed}-"))
    team = Team(workdir, args.speed, f"rf{os.getpid()}", args.stage_workers)
    log: list[dict] = []
    try:
        team.wait_ready()
        t0, cut = time.monotonic(), set()
        for _ in range(args.faults):
            inject(team, rng, cut, log, t0)
            time.sleep(rng.uniform(0.5, 4.0))
        for a, b in sorted(cut):
            team.cli("fault", "heal", a, b)
        time.sleep(SETTLE_S)
    finally:
        up_exit = team.stop()
    recordings = sorted((workdir / "rec").rglob("run.rrd"))
    result: dict = {"seed": args.seed, "stage_workers": args.stage_workers, "faults": log, "up_exit": up_exit, "workdir": str(workdir),
                    "log_errors": log_errors(workdir / "logs")}
    if recordings:
        replay = subprocess.run([AUTOPOWER, "replay", str(recordings[-1]), "--json"], env=team.env,
                                capture_output=True, text=True, timeout=120)
        s = json.loads(replay.stdout)
        result.update(recording=str(recordings[-1]), lost=s["lost_outputs"], duplicated=s["duplicated_outputs"],
                      dropped_by_budget=s["outputs"].get("held_dropped", 0),
                      superseded=s["outputs"].get("superseded", 0),
                      died_with_process=s["outputs"].get("died_with_process", 0),
                      unrecorded=s["outputs"].get("unrecorded", 0),
                      in_flight=s["outputs"].get("in_flight", 0), abandoned=s["outputs"].get("abandoned", 0),
                      outputs_recorded=sum(c["outputs"] for c in s["outputs"]["chains"].values()),
                      outputs_produced=s["outputs"].get("produced", 0),
                      energy_model_error_pct=s["energy_model_error_pct"],
                      energy_error_pct_per_robot={r: v["error_pct"] for r, v in s["energy"]["per_robot"].items()},
                      # outside the reconfiguration windows, and what the windows shifted (recording.transitions)
                      energy_steady_error_pct=s["energy_steady_error_pct"],
                      energy_transition_j=s["energy"]["transitions"]["transition_j"],
                      reconfiguration_covered_s=s["energy"]["transitions"]["covered_s"],
                      energy_metered_outside_j=s["energy"]["transitions"]["steady_metered_j"],
                      energy_model_outside_j=s["energy"]["transitions"]["steady_model_j"],
                      failed_invariants=[i for i in s["invariants"] if i["ok"] is False],
                      invariants_checked=sum(i["ok"] is not None for i in s["invariants"]),
                      energy_metered_steady_j=s["energy"]["metered_j"] - sum(s["energy"]["overhead_j"].values()),
                      energy_model_j=s["energy"]["model_j"])
    write(args, result)
    if args.json:
        print(json.dumps(result))
        return
    for entry in log:
        print(f"{entry['t_s']:6.1f} s  {entry['fault']}: exit {entry['exit']}"
              + (f" ({entry['refusal']})" if entry["refusal"] else ""))
    print(f"up exited with {up_exit}; logs and recording in {workdir}")
    if recordings:
        print(f"replay: {result['lost']} lost (besides {result['dropped_by_budget']} dropped beyond a node's hold "
              f"budget, and {result['died_with_process']} of a robot's own chain "
              f"that died with its crashed process, and {result['unrecorded']} a killed sink delivered "
              f"before it flushed their recording, {result['in_flight']} in flight at the stop and "
              f"{result['abandoned']} abandoned when their chain restarted; of {result['outputs_produced']} produced), "
              f"{result['duplicated']} duplicated; energy vs model {result['energy_model_error_pct']:+.2f} % "
              f"({result['energy_steady_error_pct']:+.2f} % outside reconfigurations, which shifted "
              f"{result['energy_transition_j']:+.1f} J) "
              f"(per robot {', '.join(f'{r} {v:+.1f}' for r, v in result['energy_error_pct_per_robot'].items())})")
        for inv in result["failed_invariants"]:
            print(f"  FAILED {inv['name']}: {inv['detail']}")
    for message, count in result["log_errors"].items():
        print(f"  {count:4d} x {message}")


if __name__ == "__main__":
    main()
