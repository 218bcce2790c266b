"""The runtime's own cost per robot: the control plane's bytes on its links and its process's own CPU.

    .venv/bin/python bench/bench_control_plane.py [--seconds S] [--lease-ms MS] [SCENARIO]

Not a timed test. A team under `up --speed 1` (the default mission in real time, link proxies, the
default lease) runs S wall seconds with its chains, then S more at rest (every chain disabled). Each robot's status says
what its links carried since the mission started (`link_bytes`, read from its sockets: TCP payload
plus each segment's IP and TCP headers) and of that the control plane's (`control_bytes`: all but
its chain packets); the figures are their growth over each window, per wall second, read from two
statuses (`autopower status --json`). Baseline, same run: the bytes of the robot's chain packets
(link minus control) while the chains run. The share of a radio's time is the model's airtime for
those bytes on that medium (`model.energy.airtime_s`, the scenario's radios): what the control
plane costs each radio. The same statuses say the CPU the robot's process spent beyond its component
code (`runtime_cpu_s`) and in it (`component_cpu_s`): the runtime's share of a core here, and of the
robot's CPU through its platform's slowdown (x50 for the paper's Sitsang), against its component
code's in the same run. At ×1 on purpose: the timers (lease, keep-alives, statuses) run on wall
time and the chains' framing on mission time, so only at ×1 do both add up as on a robot.
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import results
from bench_idle import team_status, wait_ready

from autopower.launch.summary import overhead_j
from autopower.model.control_plane import ControlPlaneSpec
from autopower.model.energy import airtime_s
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.model.parts import CPU_RUNTIME

AUTOPOWER = str(Path(sys.executable).parent / "autopower")


def counts(snap: dict) -> dict[str, tuple[float, ...]]:
    """robot -> (its status's wall time, link sent, link received, control sent, control received,
    runtime CPU s, component CPU s, the runtime's energy J, the energy of the model's steady state J)."""
    out = {}
    for robot, info in (snap.get("robots") or {}).items():
        st = info.get("status") or {}
        if st.get("link_bytes") is not None:
            energy = st.get("energy_j") or {}
            steady = sum(energy.values()) - overhead_j(st)  # the model's steady state, as the summary splits it
            out[robot] = (st["t_unix"], *st["link_bytes"], *st["control_bytes"], st.get("runtime_cpu_s", 0.0),
                          st.get("component_cpu_s", 0.0), energy.get(CPU_RUNTIME, 0.0), steady)
    return out


def rates(first: dict, second: dict) -> dict[str, dict[str, float]]:
    """Per robot, bytes and CPU seconds per wall second over the window between two readings."""
    out = {}
    for robot, (t0, *a) in first.items():
        if robot not in second or second[robot][0] <= t0:
            continue
        t1, *b = second[robot]
        dt = t1 - t0
        link_out, link_in, ctl_out, ctl_in, runtime, component, runtime_w, steady_w = (
            (y - x) / dt for x, y in zip(a, b, strict=True))
        out[robot] = {"control_out": ctl_out, "control_in": ctl_in, "chain_out": link_out - ctl_out,
                      "chain_in": link_in - ctl_in, "runtime_cpu": runtime, "component_cpu": component,
                      "runtime_w": runtime_w, "steady_w": steady_w, "window_s": dt}
    return out


UP_LEASE_MS = 500  # `autopower up`'s default lease, with 2 keep-alives per lease (launch.localhost)


def model_bytes_per_robot(scenario, lease_s: float) -> float:
    """The control plane's bytes a second per robot, sent and received, by the model's rules on the
    scenario's network (`model.control_plane`), for this team's lease and the runtime's heartbeat
    (a steady team, running or at rest, says nothing new: a status a heartbeat, `runtime.cadence`)."""
    spec = ControlPlaneSpec(enabled=True, lease_s=lease_s, keep_alives_per_lease=2)
    directed = spec.directed_bytes(build_network(scenario))
    robots = [r.name for r in scenario.robots]
    return statistics.mean(sum(b for (u, v), b in directed.items() if robot in (u, v)) for robot in robots)


DETECTION_REQUIREMENTS_S = (None, 1.0, 2.0, 5.0, 10.0)  # None: no requirement (up's 0.5 s lease, 2 s heartbeat)


def gsm_link_figures(scenario) -> list[dict]:
    """The model's control plane on one robot's GSM link to the base station (its only link there:
    Fig. 7's GSM uplink, robots meshed over 802.11a), both ways, by the mission's detection
    requirement (the lease and heartbeat it fixes, `ControlPlaneSpec.lease_for`, `heartbeat_for`),
    against issue 32's ceiling: 2 % of the radio's time."""
    gsm = scenario.radios["gsm"]
    network = build_network(scenario, "fully-connected", {"laptop-robot": "gsm", "robot-robot": "802.11a"})
    robot, base = scenario.robots[0].name, scenario.basestation
    out = []
    for requirement in DETECTION_REQUIREMENTS_S:
        if requirement is None:
            spec = ControlPlaneSpec(enabled=True, lease_s=UP_LEASE_MS / 1000.0, keep_alives_per_lease=2)
        else:
            spec = ControlPlaneSpec(enabled=True, lease_s=ControlPlaneSpec.lease_for(requirement),
                                    heartbeat_s=ControlPlaneSpec.heartbeat_for(requirement), keep_alives_per_lease=2,
                                    max_detection_s=requirement)
        directed = spec.directed_bytes(network)
        both_ways = directed[robot, base] + directed[base, robot]
        share = airtime_s(both_ways, gsm) * 100.0
        label = "none (lease 0.5 s)" if requirement is None else f"{requirement:g} s"
        print(f"  model, one GSM link both ways, detection requirement {label}: lease {spec.lease_s:g} s, heartbeat "
              f"{spec.heartbeat_s:g} s: {both_ways:,.0f} B/s, {share:.2f} % of the radio's time")
        out.append(results.figure(f"one GSM link, detection requirement {label}", share, "% of the radio's time",
                                  "2 % (issue 32's ceiling for GSM)", 2.0,
                                  group="the model's control plane on a robot's GSM uplink, by detection requirement",
                                  detail=f"lease {spec.lease_s:g} s, heartbeat {spec.heartbeat_s:g} s, "
                                         f"{both_ways:,.0f} B/s both ways",
                                  note="the model's rules (model.control_plane) with the runtime's measured sizes; "
                                       "not a measurement"))
    return out


def measure(scenario: str, seconds: float, lease_ms: int | None) -> dict[str, dict]:
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "AUTOPOWER_STATE_DIR": str(Path(tmp) / "state"), "RERUN_ANALYTICS": "0"}
        name = f"ctl{os.getpid()}"
        extra = ("--lease-ms", str(lease_ms)) if lease_ms else ()
        up = subprocess.Popen([AUTOPOWER, "up", scenario, "--speed", "1", "--team", name, "--json", "--log-dir",
                               str(Path(tmp) / "logs"), *extra], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, env=env, cwd=tmp)
        try:
            wait_ready(up, name, env)
            time.sleep(4.0)  # past the start: placement orders and the first plan are not the steady state
            first = counts(team_status(name, env))
            time.sleep(seconds)
            running = rates(first, counts(snap := team_status(name, env)))
            for chain in snap.get("running") or []:
                subprocess.run([AUTOPOWER, "chain", "disable", chain, "--team", name], env=env,
                               capture_output=True, timeout=30)
            time.sleep(6.0)  # the last frames drain, the statuses settle into their rest cadence
            first = counts(team_status(name, env))
            time.sleep(seconds)
            rest = rates(first, counts(team_status(name, env)))
            return {"running": running, "rest": rest}
        finally:
            up.send_signal(signal.SIGTERM)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                up.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario", nargs="?", default="paper-fig7")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--lease-ms", type=int, default=None, help="the Zenoh lease (default: up's)")
    results.add_json_out(parser)
    args = parser.parse_args()
    scenario = load_scenario(args.scenario)
    radios = scenario.radios
    slowdown = next((p.slowdown for p in (scenario.platforms[r.platform] for r in scenario.robots) if p.slowdown), None)
    got = measure(args.scenario, args.seconds, args.lease_ms)
    figures = []
    for phase, label in (("running", "default mission"), ("rest", "at rest (every chain disabled)")):
        per = got[phase]
        if not per:
            raise SystemExit(f"no robot reported its link bytes ({phase})")
        ctl = statistics.mean(r["control_out"] + r["control_in"] for r in per.values())
        chain = statistics.mean(r["chain_out"] + r["chain_in"] for r in per.values())
        print(f"{label}: per robot, B/s wall (sent + received)")
        for robot, r in sorted(per.items()):
            print(f"  {robot}: control {r['control_out']:8,.0f} out {r['control_in']:8,.0f} in; "
                  f"chain packets {r['chain_out']:10,.0f} out {r['chain_in']:10,.0f} in  "
                  f"(over {r['window_s']:.1f} s)")
        figures.append(results.figure(f"control plane, {label}", ctl, "B/s per robot", "chain packets (default mission)",
                                      statistics.mean(r["chain_out"] + r["chain_in"] for r in got["running"].values()),
                                      group="bytes per robot per wall second",
                                      note="the same robots' chain packets while the default mission ran, this run"))
        if phase == "running":
            print(f"  mean per robot: control {ctl:,.0f} B/s, chain packets {chain:,.0f} B/s")
        model = model_bytes_per_robot(scenario, (args.lease_ms or UP_LEASE_MS) / 1000.0)
        print(f"  the model's control plane (model.control_plane): {model:,.0f} B/s per robot, "
              f"{model / ctl:.2f} x the metered")
        figures.append(results.figure(f"the model's control plane, {label}", model, "B/s per robot",
                                      f"metered ({label})", ctl, group="bytes per robot per wall second",
                                      note="what the same robots' links carried beyond their chain packets, this "
                                           "run; running, it also holds the TCP framing and acknowledgements of the "
                                           "chain packets, which the model leaves out"))
        sent = statistics.mean(r["control_out"] for r in per.values())
        for medium, radio in sorted(radios.items()):
            share = airtime_s(sent, radio) * 100.0  # seconds of airtime per second sent
            figures.append(results.figure(f"{medium}: a robot's control sends, {label}", share, "% of the radio's time",
                                          "2 % (issue 32's ceiling for GSM)", 2.0,
                                          group="the control plane's share of each radio (sending, at x1)",
                                          note="the model's airtime for the bytes a robot sent beyond its chain "
                                               "packets per wall second"))
            print(f"  {medium:10s} {share:7.3f} % of its time sending control ({label})")
        runtime = statistics.mean(r["runtime_cpu"] for r in per.values()) * 100.0
        component = statistics.mean(r["component_cpu"] for r in got["running"].values()) * 100.0
        print(f"  runtime CPU {runtime:.2f} % of a core here per robot (its component code, default mission: "
              f"{component:.2f} %)" + (f"; x{slowdown:g} on the robot: {runtime * slowdown:.1f} % of its CPU"
                                       if slowdown else ""))
        figures.append(results.figure(f"runtime CPU, {label}", runtime, "% of a core per robot",
                                      "component code (default mission)", component,
                                      group="the runtime's own CPU per robot (x1)",
                                      note="the robot's process beyond its component code; the baseline is its "
                                           "component code's CPU while the default mission ran, this run"))
        if slowdown:
            runtime_w = statistics.mean(r["runtime_w"] for r in per.values())
            steady_w = statistics.mean(r["steady_w"] for r in got["running"].values())
            print(f"  the robot pays {runtime_w:.3f} W for it (the model's steady state, default mission: "
                  f"{steady_w:.3f} W); above 100 % of its CPU a robot could not keep up")
            figures.append(results.figure(f"runtime power on the robot, {label}", runtime_w, "W per robot",
                                          "the model's steady state (default mission)", steady_w,
                                          group="the runtime's own CPU per robot (x1)",
                                          note="metered: idle CPU, component runs, chain packets and sleeping radios "
                                               "(all but the overheads) per second, the same robots, this run"))
    figures += gsm_link_figures(scenario)
    results.write_result("control_plane", {"scenario": args.scenario, "seconds": args.seconds,
                                           "lease_ms": args.lease_ms}, figures, args.json_out,
                         what=__doc__.splitlines()[0], extra=got)


if __name__ == "__main__":
    main()
