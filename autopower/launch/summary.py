"""The summary of a team's run, from the base station's last snapshot."""

from __future__ import annotations

from autopower.model.parts import overhead_kind

KEEP_UP_THRESHOLD_PCT = 1.0  # source periods missed beyond startup jitter: the speed-up is too fast


def _sources(snap: dict) -> list[dict]:
    """Every robot's source statistics in a snapshot (`protocol.SourceStats` as a dict)."""
    return [s for info in (snap.get("robots") or {}).values()
            for s in ((info.get("status") or {}).get("sources") or {}).values()]


def missed_periods(snap: dict) -> tuple[int, int, float]:
    """(frames produced, periods missed, missed %) over every robot's sources in a snapshot."""
    sources = _sources(snap)
    produced = sum(s.get("produced_total", 0) for s in sources)
    missed = sum(s.get("missed", 0) for s in sources)
    return produced, missed, (100.0 * missed / (produced + missed) if produced + missed else 0.0)


def missed_while_stopped(snap: dict) -> int:
    """Of the periods missed, those agents found when they came back from being stopped (a frozen
    agent, a suspended host): the speed-up is not to blame for them."""
    return sum(s.get("missed_stopped", 0) for s in _sources(snap))


def missed_for_backlog(snap: dict) -> int:
    """Of the periods missed, the captures sources skipped because the first stage had not yet run
    what they held for it (its custody full: `Custody.has_room`), over every robot."""
    return sum(((info.get("status") or {}).get("counters") or {}).get("missed-periods-backlog", 0)
               for info in (snap.get("robots") or {}).values())


def keep_up_warning(snap: dict, speed: float) -> str | None:
    """What to tell the user when this machine cannot keep up with the chosen speed-up, else None.

    Periods missed while an agent was stopped (`fault freeze`, a suspended host) do not count: a
    freeze of two seconds at x10 misses a hundred camera periods on any machine.
    """
    produced, missed, _ = missed_periods(snap)
    slow = missed - missed_while_stopped(snap)
    pct = 100.0 * slow / (produced + missed) if produced + missed else 0.0
    if pct <= KEEP_UP_THRESHOLD_PCT:
        return None
    backlog = missed_for_backlog(snap)
    why = (f", {backlog} of them skipped because a stage had not run the frames its source held for it"
           if backlog else "")
    return (f"{slow} source periods missed ({pct:.1f} %) with no agent stopped{why}: this machine cannot keep up "
            f"with --speed {speed:g}; lower --speed (and use --energy-scale for shorter missions)")


def every_robot_depleted(snap: dict) -> bool:
    robots = (snap.get("robots") or {}).values()
    return bool(robots) and all((info.get("status") or {}).get("depleted") for info in robots)


def status_line(snap: dict, speed: float) -> str:
    """One plain line for a log or a pipe: virtual time, batteries, results, misses."""
    batteries = []
    for name, info in (snap.get("robots") or {}).items():
        st = info.get("status") or {}
        if st.get("initial_j"):
            batteries.append(f"{name} {max(0.0, st['battery_j'] / st['initial_j']):.0%}" + (" depleted" if st.get("depleted") else ""))
        else:
            batteries.append(f"{name} {'joining' if info.get('present') else 'absent'}")
    results = sum(s.get("received_total", 0) for s in ((snap.get("basestation") or {}).get("sinks") or {}).values())
    _, missed, pct = missed_periods(snap)
    stopped = missed_while_stopped(snap)
    line = (f"t={snap.get('t_virtual') or 0:.0f}s virtual (x{speed:g}) {'ready' if snap.get('ready') else 'placing'}; "
            f"batteries: {', '.join(batteries) or '-'}; operator results {results}; missed {missed} ({pct:.1f} %"
            + (f", {stopped} of them while an agent was stopped)" if stopped else ")"))
    warning = keep_up_warning(snap, speed)
    if snap.get("recording_error"):
        line += f"; RECORDING FAILED: {snap['recording_error']}"
    if (snap.get("supervision") or {}).get("crashes"):
        line += f"; {supervisor_line(snap['supervision'])}"
    return line + (f"; warning: {warning}" if warning else "")


def supervisor_line(supervision: dict) -> str:
    """What the launcher's supervisor did, in one line (crashes, restarts, what it gave up on)."""
    restarts = ", ".join(f"{n} {k}x" for n, k in (supervision.get("restarts") or {}).items()) or "none"
    line = f"supervisor: {supervision.get('crashes', 0)} crash(es), restarts {restarts}"
    if supervision.get("down"):
        line += f", restarting {', '.join(supervision['down'])}"
    given_up = supervision.get("given_up") or {}
    if given_up:
        line += "; GAVE UP on " + "; ".join(f"{n} ({why})" for n, why in given_up.items())
    return line


def overhead_j(status: dict) -> float:
    """The energy a status's meter charged outside the model's steady state (migrations, recovery,
    the control plane: `model.parts.overhead_kind`)."""
    return sum(float(j) for part, j in (status.get("energy_j") or {}).items() if overhead_kind(part) is not None)


def placed_power_w(status: dict, at_ready: dict | None, *, overheads: bool = False) -> float | None:
    """A robot's metered mean power since the team was ready (every stage where the plan wants it,
    the configuration the model predicts a power for), from two of its own statuses: battery and
    virtual time each from the same status, less what it charged outside the model's steady state
    (with ``overheads``: that part alone). None without a usable status at ready."""
    before = (at_ready or {}).get("status") or {}
    b0, t0 = before.get("battery_j"), before.get("t_virtual")
    b1, t1 = status.get("battery_j"), status.get("t_virtual")
    if None in (b0, t0, b1, t1) or t1 - t0 <= 0:
        return None
    over = overhead_j(status) - overhead_j(before)
    return (over if overheads else (b0 - b1) - over) / (t1 - t0)


def _usable(robot: dict | None, name: str, at_ready: dict) -> bool:
    """Whether a robot's status can start its power comparison: it has a battery and a mission
    clock, and the robot sent it running the plan the team was ready with (that plan's epoch or a
    later one, and every stage the ready snapshot places on it running). A status from before
    that (a robot in a large fleet reports every 0.5 s; the ready plan reached it after its last
    one) would count its start-up as the placed configuration: at 30 robots the last robots to get
    their stages read 2 % below the model for it."""
    status = (robot or {}).get("status") or {}
    if status.get("battery_j") is None or status.get("t_virtual") is None:
        return False
    epoch = at_ready.get("epoch")
    if epoch is not None and (status.get("plan_epoch") is None or status["plan_epoch"] < epoch):
        return False
    hosted = status.get("hosted") or {}
    return all(hosted.get(stage) == "running" for stage, node in (at_ready.get("placement") or {}).items()
               if node == name)


def at_ready_complete(at_ready: dict) -> bool:
    """Whether every robot of the ready snapshot has a status to compare its power from."""
    return all(_usable(robot, name, at_ready) for name, robot in (at_ready.get("robots") or {}).items())


def complete_at_ready(at_ready: dict, snap: dict) -> None:
    """Give each robot whose status in the ready snapshot cannot start its comparison (`_usable`:
    no battery or mission clock yet, or sent before it ran the ready plan) its first later status
    that can: its power is compared with the model's from then on, not left out."""
    robots = at_ready.setdefault("robots", {})
    for name, info in (snap.get("robots") or {}).items():
        if not _usable(robots.get(name), name, at_ready) and _usable(info, name, at_ready):
            robots[name] = info


def run_summary(snap: dict, *, team: str, speed: float, ready_after_s: float, wall_s: float,
                exit_codes: dict | None = None, log_dir: str = "", at_ready: dict | None = None) -> dict:
    """The JSON summary of a run: placement, batteries vs the model, sources, sinks, errors.

    ``at_ready``: the snapshot taken when the team was first ready. ``power_error`` compares the
    power metered since then, less the overheads the model leaves out (``placed_overhead_w``, as
    the replay does), with the model's for the plan (``placed_power_w``); the start-up before
    it (no stage placed yet: seconds of virtual time, more on a loaded machine) is in
    ``mean_power_w``, the whole run's mean, but not in the comparison."""
    robots = {}
    for name, info in snap.get("robots", {}).items():
        st = info.get("status") or {}
        initial, battery, t = st.get("initial_j"), st.get("battery_j"), st.get("t_virtual") or 0.0
        consumed = (initial - battery) if initial is not None and battery is not None else None
        measured = consumed / t if consumed is not None and t > 0 else None
        placed = placed_power_w(st, ((at_ready or {}).get("robots") or {}).get(name))
        compared = placed if at_ready is not None else measured
        predicted = info.get("predicted_w")
        robots[name] = {
            "present": info.get("present"), "departed": info.get("departed"),
            "initial_j": initial, "battery_j": battery, "consumed_j": consumed, "t_virtual": t,
            "mean_power_w": measured, "placed_power_w": placed, "predicted_w": predicted,
            # beside the comparison: what it charged over the same time outside the model's steady
            # state (migrations, recovery, its control plane), in W
            "placed_overhead_w": placed_power_w(st, ((at_ready or {}).get("robots") or {}).get(name), overheads=True),
            "power_error": (compared / predicted - 1) if compared and predicted else None,
            "window_power_w": sum(st.get("power_w", {}).values()) if st else None,
            "cpu_utilisation": st.get("cpu_utilisation"), "hosted": st.get("hosted", {}),
            "sources": st.get("sources", {}), "sinks": st.get("sinks", {}),
            "errors": st.get("errors", {}), "counters": st.get("counters", {}),
            "energy_by_part_j": st.get("energy_j", {}),
            "cpu_s": process_cpu_s(st),
            "links": link_totals(st),
        }
    base = snap.get("basestation") or {}
    produced, missed, missed_pct = missed_periods(snap)
    warning = keep_up_warning(snap, speed)
    return {
        "team": team, "scenario": snap.get("scenario"), "accounting": snap.get("accounting"), "speed": speed,
        "policy": snap.get("policy"),
        "ready": snap.get("ready"), "ready_after_s": ready_after_s, "wall_s": wall_s,
        "t_virtual": snap.get("t_virtual"),
        "placement": snap.get("placement"), "target": snap.get("target"), "media": snap.get("media"),
        "running": snap.get("running"), "disabled": snap.get("disabled"),
        "planned_lifetime_s": snap.get("planned_lifetime_s"), "predicted_lifetime_s": snap.get("predicted_lifetime_s"),
        "reasons": snap.get("reasons"),
        "robots": robots,
        "basestation": {"sinks": base.get("sinks", {}), "errors": base.get("errors", {}),
                        "counters": base.get("counters", {}), "hosted": base.get("hosted", {}),
                        "compute_ms": base.get("compute_ms", {}), "cpu_s": process_cpu_s(base)},
        "frames_produced": produced, "periods_missed": missed,
        "periods_missed_while_stopped": missed_while_stopped(snap),
        "periods_missed_backlog": missed_for_backlog(snap),
        "missed_ratio": missed / (produced + missed) if produced + missed else 0.0,
        "missed_periods_pct": round(missed_pct, 2),
        "warnings": [warning] if warning else [],
        "migrations_done": snap.get("migrations_done"), "downtime_ms": snap.get("downtime_ms"),
        "replans": snap.get("replans"), "first_depletion": snap.get("first_depletion"),
        "events": snap.get("events"), "exit_codes": exit_codes or {}, "log_dir": log_dir,
    }


def link_totals(status: dict) -> dict[str, int]:
    """What a node's links carried since the mission started in its process, as its kernel counted
    them (`runtime.link_traffic`): bytes and TCP segments (packets) each way, and of the bytes the
    control plane's (all but the chain packets). Zeros where nothing could be read."""
    out = {}
    for field, name in (("link_bytes", "bytes"), ("link_packets", "packets"), ("control_bytes", "control_bytes")):
        sent, received = status.get(field) or (0, 0)
        out[f"{name}_sent"], out[f"{name}_received"] = int(sent), int(received)
    return out


def process_cpu_s(status: dict) -> dict[str, float]:
    """A node's CPU seconds on this computer since the mission started in its process (a restarted
    process counts from its own start): the runtime's and its component code's (`NodeStatus`)."""
    return {"runtime": status.get("runtime_cpu_s", 0.0), "components": status.get("component_cpu_s", 0.0)}


def team_sinks(snap: dict) -> list[dict]:
    """Every sink ledger in a base-station snapshot: the robots' (results held for an unreachable
    operator) and the base station's."""
    statuses = [v["status"] for v in snap.get("robots", {}).values() if v.get("status")]
    if snap.get("basestation"):
        statuses.append(snap["basestation"])
    return [ledger for status in statuses for ledger in status.get("sinks", {}).values()]


def lost_outputs(sinks) -> int:
    """Outputs a sink never received: every seq up to the highest one seen should have arrived once."""
    return sum(max(0, ledger["max_seq"] + 1 - ledger["received"]) for ledger in sinks)


def chain_latencies(snap: dict) -> dict[str, dict]:
    """Each chain's end-to-end latency (its source's capture to its sink's receipt, wall ms), where
    its sink is: ``{chain: {"sink", "outputs", "p50_ms", "max_ms", "missing", "duplicated"}}``.

    The base station's sink counts; a robot's holds results for an unreachable operator and is
    shown only for a chain the base station has no sink of.
    """
    out: dict[str, dict] = {}
    holders = [(snap.get("basestation") or {}, None)]
    holders += [((v.get("status") or {}), name) for name, v in (snap.get("robots") or {}).items()]
    for status, node in holders:
        for chain, s in (status.get("sinks") or {}).items():
            if chain in out:
                continue
            out[chain] = {"sink": node or "base station", "outputs": s.get("received_total", 0),
                          "p50_ms": s.get("latency_ms_p50"), "max_ms": s.get("latency_ms_max"),
                          "missing": max(0, s.get("max_seq", -1) + 1 - s.get("received", 0)),
                          "duplicated": s.get("duplicates_total", 0)}
    return dict(sorted(out.items()))
