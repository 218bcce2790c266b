"""`autopower demo`: the whole story in one command.

Three agents and the base station on this machine (the same launcher as `autopower up`, every
link through its own LinkProxy), the paper's mission with time acceleration and a battery small
enough to end in about a minute, then:

1. cut r1's link to the base station silently: the team detects it and reconfigures (r1 stays
   in the team through another robot's agent); heal;
2. cut every robot from the base station: the robots form a subgroup and agree on a
   reallocation among themselves (propose -> accept -> commit); heal: the base station adopts
   what they run;
3. SIGKILL one robot's agent (``crash-agent``): the launcher's supervisor starts it again, it
   rejoins with its battery as it was (not the mission's starting energy) and its chains resume,
   nothing lost or duplicated;
4. SIGKILL the base station (``crash-basestation``; ``--no-crash-basestation`` skips it): the
   robots carry on through a subgroup reallocation, the supervisor starts a new base station and
   it takes the running team over (its clock, placement and epochs; ``taken_over_wall_s``);
5. run until the first robot's battery is empty;
6. stop, merge the recording and print the replay summary (``--json``: one object).
"""

from __future__ import annotations

import logging
import os
import re
import signal
import sys
import time
from datetime import datetime
from pathlib import Path

from autopower.errors import AutoPowerError
from autopower.launch.summary import lost_outputs, run_summary

log = logging.getLogger(__name__)

SCENARIO = "paper-fig7"
_COMMIT = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) INFO autopower.runtime.subgroup: subgroup (\S+): round (\S+) committed")
_BASE_OUT = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) INFO autopower.agent.process: agent (\S+): "
                       r"base station \S+ out of sight")
TAKEOVER_WAIT_S = 15.0  # how long the demo waits for a restarted base station to adopt the team


def _wait(team, predicate, timeout_s: float, what: str, unless=None) -> dict:
    """The first snapshot ``predicate`` accepts; or, once ``unless()`` is true (asked whether or
    not the base station answers), the last snapshot it gave ({} if none)."""
    deadline = time.monotonic() + timeout_s
    snap: dict = {}
    while time.monotonic() < deadline:
        team.check_children()
        try:
            snap = team.snapshot(timeout_s=2.0)
        except AutoPowerError:
            if unless is not None and unless():
                return snap
            continue
        if predicate(snap) or (unless is not None and unless()):
            return snap
        time.sleep(0.05)
    raise AutoPowerError(f"demo: timed out after {timeout_s:g} s waiting for {what} (logs in {team.log_dir})")


def _snapshot_or(team, last: dict) -> dict:
    """A fresh snapshot, or ``last`` when the base station does not answer (it may be starting)."""
    try:
        return team.snapshot(timeout_s=2.0)
    except AutoPowerError:
        return last


def _handled(snap: dict, before: int, kind: str, target: str | None = None) -> list[dict]:
    return [f for f in snap.get("faults", [])[before:]
            if f["kind"] == kind and (target is None or f["target"] == target) and f["reconfigured_unix"]]


def _commits(log_dir: Path, robots: list[str], pattern: re.Pattern = _COMMIT) -> list[tuple[float, str, str]]:
    """(wall time, node, round) of every subgroup commit in the agents' logs (or what `pattern` matches)."""
    out = []
    for robot in robots:
        try:
            lines = (log_dir / f"{robot}.log").read_text(errors="replace").splitlines()
        except OSError:
            continue
        for line in lines:
            m = pattern.match(line)
            if m:
                t = datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
                out.append((t, m.group(2), m.group(3) if pattern.groups >= 3 else ""))
    return sorted(out)


def _interrupt(signum, _frame):
    raise KeyboardInterrupt


def _restarted_at(team, node: str, after: float) -> float | None:
    """Wall time the supervisor started `node` again after `after` (None: not yet)."""
    return next((e.t_unix for e in team.supervisor.events
                 if e.node == node and e.kind == "restarted" and e.t_unix >= after), None)


def crash_agent(team, faults, robots: list[str], quiet: bool) -> dict:
    """SIGKILL the agent hosting most stages; wait until it is back, its battery and chains resumed."""
    snap = team.snapshot()
    hosts = list(snap["placement"].values())
    victim = max(robots, key=lambda r: (hosts.count(r), r == "r2"))
    status = snap["robots"][victim]["status"]
    battery_before = status["battery_j"]
    produced_before = sum(s["produced_total"] for s in status["sources"].values())
    before = len(snap["faults"])
    _say(quiet, f"demo: SIGKILL {victim}'s agent (hosting {hosts.count(victim)} stage(s))")
    t_kill = faults.apply({"op": "crash", "robot": victim})["fault"]["t_unix"]

    def back(s: dict) -> bool:
        restarted = _restarted_at(team, victim, t_kill)
        st = s["robots"][victim].get("status") or {}
        return (restarted is not None and s["robots"][victim]["present"] and s["ready"]
                and st.get("t_unix", 0) > restarted and st.get("plan_epoch") == s["epoch"]
                and sum(x["produced_total"] for x in st["sources"].values()) > produced_before)

    snap = _wait(team, back, 30, f"{victim} restarted and back in the team")
    t_back = time.time()
    left = [f for f in snap["faults"][before:] if f["kind"] == "node-left" and f["target"] == victim]
    battery_after = snap["robots"][victim]["status"]["battery_j"]
    entry = {"kind": "crash-agent", "target": victim, "parts": [victim],
             "detected_wall_s": (left[0]["detected_unix"] - t_kill) if left else None,
             "reconfigured_wall_s": (left[0]["reconfigured_unix"] - t_kill) if left and left[0]["reconfigured_unix"]
             else None,
             "reconfigured_by": f"plan epoch {left[0]['epoch']}" if left else None,
             "restarted_wall_s": _restarted_at(team, victim, t_kill) - t_kill,
             "rejoined_wall_s": t_back - t_kill,
             "battery_before_j": battery_before, "battery_after_j": battery_after}
    _say(quiet, f"demo:   detected after {_fmt(entry['detected_wall_s'])} s, restarted after "
                f"{entry['restarted_wall_s']:.3f} s, back with its chains after {entry['rejoined_wall_s']:.3f} s; "
                f"battery {battery_before:,.0f} J before, {battery_after:,.0f} J after (not reset)")
    return entry


def crash_basestation(team, faults, robots: list[str], quiet: bool, log_dir: Path) -> dict:
    """SIGKILL the base station: the robots reallocate among themselves; a new one is started.

    Waits at most `TAKEOVER_WAIT_S` for the new base station to adopt the running team (its
    snapshot on the same mission clock, ready, robots present).
    """
    base = team.scenario.basestation
    mission = team.snapshot()["mission"]
    seen_before = len(_commits(log_dir, robots, _BASE_OUT))
    commits_before = len(_commits(log_dir, robots))
    _say(quiet, f"demo: SIGKILL the base station {base}")
    t_kill = faults.apply({"op": "crash", "robot": base})["fault"]["t_unix"]
    deadline = time.monotonic() + 10
    seen, commits = [], []
    while time.monotonic() < deadline:
        team.check_children()
        seen = _commits(log_dir, robots, _BASE_OUT)[seen_before:]
        commits = _commits(log_dir, robots)[commits_before:]
        if commits and _restarted_at(team, base, t_kill):
            break
        time.sleep(0.1)
    restarted = _restarted_at(team, base, t_kill)
    taken_over = None
    if restarted is not None:  # a new base station: has it adopted the running team and its clock?
        deadline = time.monotonic() + TAKEOVER_WAIT_S
        while time.monotonic() < deadline and taken_over is None:
            team.check_children()
            try:
                s = team.snapshot(timeout_s=1.0)
            except AutoPowerError:
                continue
            present = [r for r in robots if (s.get("robots", {}).get(r) or {}).get("present")]
            if (s.get("mission") or {}).get("epoch_unix") == mission["epoch_unix"] and s.get("ready") and present:
                taken_over = time.time()
            time.sleep(0.1)
    entry = {"kind": "crash-basestation", "target": base, "parts": [base],
             "detected_wall_s": (min(t for t, _, _ in seen) - t_kill) if seen else None,
             "reconfigured_wall_s": (min(t for t, _, _ in commits) - t_kill) if commits else None,
             "reconfigured_by": f"subgroup round {commits[0][2]}" if commits else None,
             "restarted_wall_s": (restarted - t_kill) if restarted else None,
             "taken_over_wall_s": (taken_over - t_kill) if taken_over else None}
    _say(quiet, f"demo:   robots saw it after {_fmt(entry['detected_wall_s'])} s and reallocated among themselves "
                f"after {_fmt(entry['reconfigured_wall_s'])} s; a new base station started after "
                f"{_fmt(entry['restarted_wall_s'])} s; "
                + (f"it took over the team after {entry['taken_over_wall_s']:.3f} s" if taken_over
                   else f"it has not adopted the running team within {TAKEOVER_WAIT_S:g} s"))
    return entry


def _fmt(x: float | None) -> str:
    return "?" if x is None else f"{x:.3f}"


def _say(quiet: bool, text: str) -> None:
    if not quiet:
        print(text, file=sys.stderr, flush=True)


RUNTIME_MARGIN = 1.4


def run_demo(*, speed: float, mission_wall_s: float, lease_ms: int, log_dir: Path, record: bool,
             quiet: bool, policy: str = "rebalance", secure: bool = True, testbed: bool = False,
             crash_base: bool = False, stage_workers: str = "auto", transport: str = "tls") -> dict:
    from autopower.launch.faults import FaultController
    from autopower.launch.localhost import LocalTeam, TeamSpec
    from autopower.model.loading import load_scenario
    from autopower.planner import PlanRequest, plan

    started = time.monotonic()
    full = load_scenario(SCENARIO)
    lifetime = plan(PlanRequest(scenario=full)).evaluation.lifetime_s
    # the planned mission lasts about mission_wall_s; the model leaves out the robots' own runtime CPU
    # (x50 on the Sitsang: about 40 % more power at x10, measured), so the batteries are sized with
    # that margin, or the robots run dry before the story's last fault (a base station's takeover)
    energy_scale = mission_wall_s * speed / lifetime * RUNTIME_MARGIN
    scenario = full.with_energies({r.name: r.energy_j * energy_scale for r in full.robots})
    robots = [r.name for r in scenario.robots]
    base = scenario.basestation
    # the recording id derives from the run directory's name: one name per run
    record_dir = log_dir / f"run-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}" if record else None
    spec = TeamSpec(scenario=SCENARIO, speed=speed, energy_scale=energy_scale, lease_ms=lease_ms,
                    proxied_links=True, log_dir=log_dir, record_dir=record_dir, policy=policy, secure=secure,
                    stage_workers=stage_workers, transport=transport)
    faults_out: list[dict] = []
    adopted = 0
    if testbed:  # each node in its network namespace, links shaped like their radios (root)
        from autopower.launch.testbed import TestbedTeam

        team = TestbedTeam(spec, scenario)
    else:
        team = LocalTeam(spec, scenario)
    snap: dict = {}
    previous = signal.signal(signal.SIGTERM, _interrupt)  # a terminated demo still stops its team (and testbed)
    try:
        team.start()
        _say(quiet, f"demo: base station + {len(robots)} agents (team {team.team}, logs in {log_dir}), "
                    f"speed {speed:g}x, mission ~{mission_wall_s:g} s, policy {policy}")
        team.wait_ready(60)
        mission_started = time.monotonic()  # batteries drain from here; start-up under load varies
        faults = FaultController(team)
        time.sleep(3.0)

        # 1. one silent cut: detection, replanning around it (relay), heal
        before = len(team.snapshot()["faults"])
        t_cut = faults.apply({"op": "cut", "a": "r1", "b": base})["fault"]["t_unix"]
        _say(quiet, f"demo: cut r1-{base}")
        snap = _wait(team, lambda s: _handled(s, before, "link-down"), 10, "the cut to be handled")
        fault = _handled(snap, before, "link-down")[0]
        faults_out.append({"kind": "cut", "target": f"r1-{base}", "parts": [f"r1-{base}"],
                           "detected_wall_s": fault["detected_unix"] - t_cut,
                           "reconfigured_wall_s": fault["reconfigured_unix"] - t_cut,
                           "reconfigured_by": f"plan epoch {fault['epoch']}"})
        _say(quiet, f"demo:   detected after {faults_out[-1]['detected_wall_s']:.3f} s, reconfigured after "
                    f"{faults_out[-1]['reconfigured_wall_s']:.3f} s; r1 present: {snap['robots']['r1']['present']}")
        time.sleep(1.5)
        faults.apply({"op": "heal", "a": "r1", "b": base})
        _wait(team, lambda s: not s["links_down"] and s["ready"], 15, "the healed link back in the plan")
        _say(quiet, "demo: healed r1-" + base)
        time.sleep(1.0)

        # 2. every robot cut from the base station: subgroup agreement without it
        commits_before = len(_commits(log_dir, robots))
        before = len(team.snapshot()["faults"])
        t_cut = time.time()
        for r in robots:
            faults.apply({"op": "cut", "a": r, "b": base})
        # how long the cuts took to be in place (the kernel's routing lock is shared with every other
        # namespace being made or removed on the machine); the times below still count from t_cut
        cut_applied_s = time.time() - t_cut
        _say(quiet, "demo: cut every robot from the base station")
        deadline = time.monotonic() + 10
        commits = []
        while time.monotonic() < deadline:
            commits = _commits(log_dir, robots)[commits_before:]
            if {node for _, node, _ in commits} >= set(robots):
                break
            time.sleep(0.1)
        if not commits:
            raise AutoPowerError(f"demo: no subgroup agreement within 10 s (logs in {log_dir})")
        # The base station loses every robot at its own lease, which may end after the robots' rounds
        # committed: asked too soon it has not seen them go (its answer may also wait on links Zenoh
        # is closing). Waited for up to 10 s; a robot it still has not lost leaves detection unknown.
        def lost_of(s: dict) -> list[dict]:
            return [f for f in s["faults"][before:] if f["kind"] == "node-left"]

        give_up = time.monotonic() + 10
        snap = _wait(team, lambda s: len(lost_of(s)) >= len(robots), 12, "the base station's answer after the cut",
                     unless=lambda: time.monotonic() > give_up)
        lost = lost_of(snap) if snap else []
        detected = max(f["detected_unix"] for f in lost) if len(lost) >= len(robots) else None
        faults_out.append({"kind": "cut", "target": ",".join(f"{r}-{base}" for r in robots),
                           "parts": [f"{r}-{base}" for r in robots],
                           "detected_wall_s": (detected - t_cut) if detected else None,
                           # the commit point of the two-phase commit: the leader's decision (the
                           # first "committed" line); members apply it as it reaches them
                           "reconfigured_wall_s": min(t for t, _, _ in commits) - t_cut,
                           "applied_by_every_member_wall_s": max(t for t, _, _ in commits) - t_cut,
                           "cut_applied_wall_s": cut_applied_s,
                           "reconfigured_by": f"subgroup round {commits[0][2]}"})
        _say(quiet, f"demo:   subgroup {commits[0][2]} committed by {len({n for _, n, _ in commits})} robots "
                    f"{faults_out[-1]['reconfigured_wall_s']:.3f} s after the cut")
        time.sleep(2.0)
        for r in robots:
            faults.apply({"op": "heal", "a": r, "b": base})
        snap = _wait(team, lambda s: s["ready"] and all(v["present"] for v in s["robots"].values())
                     and not s["links_down"], 20, "the team back under the base station")
        # the base station may call the team back (links up, robots present) a moment before the
        # robots' first statuses since the heal say what the subgroup runs: give them a few status
        # periods, since a snapshot taken at once may still say 0 adopted
        try:
            snap = _wait(team, lambda s: s.get("adopted", 0) > 0, 3.0, "the subgroup's stages adopted")
        except AutoPowerError:
            pass  # the subgroup moved nothing the base station did not already place: 0 is the answer
        adopted = snap.get("adopted", 0)  # (a base station started later knows nothing of this)
        _say(quiet, f"demo: healed; the base station adopted {adopted} stage(s) the subgroup ran")

        # 3. an agent crashes: restarted by the supervisor, it rejoins where it was
        time.sleep(1.0)
        faults_out.append(crash_agent(team, faults, robots, quiet))
        time.sleep(1.0)

        # 4. the base station crashes: the robots carry on in a subgroup, the supervisor starts a
        # new one, which learns what the robots run and takes the team over (basestation/takeover.py)
        if crash_base:
            faults_out.append(crash_basestation(team, faults, robots, quiet, log_dir))

        # 5. the rest of the mission
        remaining = max(5.0, mission_wall_s + 15 - (time.monotonic() - mission_started))
        # A robot that runs dry leaves (its agent exits 0): on a loaded machine that can happen
        # while the restarted base station is still starting, and it will never hear of it.
        snap = _wait(team, lambda s: bool(s.get("first_depletion")), remaining, "the first robot to run dry",
                     unless=lambda: bool(team.exited_cleanly() & set(robots))) or snap
        time.sleep(0.6)  # its last status and the base's reaction
        snap = _snapshot_or(team, snap)
        dry = snap.get("first_depletion")
        _say(quiet, f"demo: {dry['robot']} ran dry at t={dry['t_virtual']:.0f} s" if dry else
             f"demo: {', '.join(sorted(team.exited_cleanly() & set(robots)))} ran dry while no base station "
             "was up to see it (the recording says when)")
    finally:
        try:
            codes = team.stop()
        finally:
            signal.signal(signal.SIGTERM, previous)

    summary = run_summary(snap, team=team.team, speed=speed, ready_after_s=-1.0,
                        wall_s=time.monotonic() - started, exit_codes=codes, log_dir=str(log_dir))
    sinks = dict(summary["basestation"]["sinks"])
    for info in summary["robots"].values():
        sinks.update(info["sinks"])
    duplicated = sum(s.get("duplicates_total", 0) for s in sinks.values())
    lost = lost_outputs(sinks.values())
    # energy: metered consumption of each robot against the model's power for the plan it ran
    errors = [abs(r["power_error"]) for r in summary["robots"].values() if r["power_error"] is not None]
    live = {"faults": faults_out, "migrations": snap.get("migrations_done", 0), "lost_outputs": lost,
            "duplicated_outputs": duplicated,
            "energy_model_error_pct": (max(errors) * 100.0) if errors else None,
            "first_depletion": snap.get("first_depletion")}
    result = {
        "agents": len(robots), "wall_s": time.monotonic() - started, "log_dir": str(log_dir),
        "adopted": adopted, "first_depletion": snap.get("first_depletion"), "live": live,
        # without a recording the live measurements are all there is
        "source": "live", "recording": None, "faults": faults_out, "migrations": live["migrations"],
        "lost_outputs": lost, "duplicated_outputs": duplicated,
        "energy_model_error_pct": live["energy_model_error_pct"],
        # what every link of this run was: mutual TLS + default-deny access control, or plain tcp
        "security": "mtls+acl" if secure else "insecure",
    }
    if testbed:
        net = team.net
        result["testbed"] = {"run": net.run_id, "namespaces": net.namespaces, **net.describe()}
    result["supervision"] = team.supervision()
    if record_dir is not None:
        result.update(_recording(record_dir, quiet))
        dry = result.get("first_dry")
        if result["first_depletion"] is None and dry:  # no base station was up to see it: the recording saw it
            result["first_depletion"] = {"robot": dry["robot"], "t_virtual": dry["at_s"], "seen_by": "recording"}
        # what only the launcher knows (restart, rejoin, takeover) joins the replay's view of the crashes
        live_crashes = {(f["kind"], f["target"]): f for f in faults_out if f["kind"].startswith("crash-")}
        for fault in result["faults"]:
            extra = live_crashes.pop((fault["kind"], fault["target"]), None)
            for key, value in (extra or {}).items():
                fault.setdefault(key, value)
        result["faults"].extend(live_crashes.values())  # not in the recording (e.g. it could not be merged)
    return result


def _recording(record_dir: Path, quiet: bool) -> dict:
    """The run's story as the replay of its recording tells it (one source of truth for the
    summary, the same code as `autopower replay`)."""
    out: dict = {}
    try:
        import warnings

        from autopower.recording.live import merge_run
        from autopower.recording.replay import replay_summary

        with warnings.catch_warnings():  # the files of the processes the demo SIGKILLed have no footer
            warnings.filterwarnings("ignore", message="RRD file has no footer")
            merged = merge_run(record_dir)
        out["recording"] = str(merged)
        replay = replay_summary(merged)
    except Exception as exc:  # noqa: BLE001 - the demo's live figures stand without the recording
        _say(quiet, f"demo: recording/replay unavailable: {exc}")
        out["recording_error"] = str(exc)
        return out
    out.update(story_from_replay(replay))
    out["replay"] = replay
    return out


def story_from_replay(replay: dict) -> dict:
    """The demo's summary fields, computed from a replay summary."""
    dry = replay.get("first_dry")
    return {
        "source": "recording",
        "faults": [{key: f[key] for key in ("kind", "target", "parts", "at_mission_s", "detected_wall_s",
                                            "reconfigured_wall_s", "detected_mission_s", "reconfigured_mission_s",
                                            "reconfigured_by")}
                   for f in replay["faults"]],
        "migrations": replay["migrations"]["count"],
        "migration_downtime_ms_max": replay["migrations"]["downtime_ms_max"],
        "lost_outputs": replay["lost_outputs"],
        "duplicated_outputs": replay["duplicated_outputs"],
        "outputs": sum(c["outputs"] for c in replay["outputs"]["chains"].values()),
        "energy_model_error_pct": replay["energy_model_error_pct"],
        # the same outside the reconfigurations, and what they shifted (`recording.transitions`)
        "energy_steady_error_pct": replay["energy_steady_error_pct"],
        "transition_j": replay["energy"]["transitions"]["transition_j"],
        "recovery_j": replay["energy"]["overhead_j"].get("recovery"),
        # first runs of inputs that waited through a reconfiguration, on the host a stage restarted on
        "backlog_j": replay["energy"]["overhead_j"].get("backlog"),
        # the control plane: what each robot's links carried beyond its chain packets (measured), and
        # the energy its radios paid for it, apart from the model
        "control_j": replay["energy"]["overhead_j"].get("control"),
        "control_bytes": {r: e.get("control_bytes") for r, e in replay["energy"]["per_robot"].items()},
        # the runtime's own CPU (each robot's process beyond its component code) and what the
        # robots' batteries paid for it through their platform's slowdown, apart from the model
        "runtime_j": replay["energy"]["overhead_j"].get("runtime"),
        "cpu_s": {r: e.get("cpu_s") for r, e in replay["energy"]["per_robot"].items()},
        "first_dry": dry,
    }
