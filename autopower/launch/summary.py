"""The summary of a team's run, from the base station's last snapshot."""

from __future__ import annotations


def run_summary(snap: dict, *, team: str, speed: float, ready_after_s: float, wall_s: float,
              exit_codes: dict | None = None, log_dir: str = "") -> dict:
    """The JSON summary of a run: placement, batteries vs the model, sources, sinks, errors."""
    robots = {}
    for name, info in snap.get("robots", {}).items():
        st = info.get("status") or {}
        initial, battery, t = st.get("initial_j"), st.get("battery_j"), st.get("t_virtual") or 0.0
        consumed = (initial - battery) if initial is not None and battery is not None else None
        measured = consumed / t if consumed is not None and t > 0 else None
        predicted = info.get("predicted_w")
        robots[name] = {
            "present": info.get("present"), "departed": info.get("departed"),
            "initial_j": initial, "battery_j": battery, "consumed_j": consumed, "t_virtual": t,
            "mean_power_w": measured, "predicted_w": predicted,
            "power_error": (measured / predicted - 1) if measured and predicted else None,
            "window_power_w": sum(st.get("power_w", {}).values()) if st else None,
            "cpu_utilisation": st.get("cpu_utilisation"), "hosted": st.get("hosted", {}),
            "sources": st.get("sources", {}), "sinks": st.get("sinks", {}),
            "errors": st.get("errors", {}), "counters": st.get("counters", {}),
            "energy_by_part_j": st.get("energy_j", {}),
        }
    base = snap.get("basestation") or {}
    produced = sum(s.get("produced_total", 0) for r in robots.values() for s in r["sources"].values())
    missed = sum(s.get("missed", 0) for r in robots.values() for s in r["sources"].values())
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
                        "compute_ms": base.get("compute_ms", {})},
        "frames_produced": produced, "periods_missed": missed,
        "missed_ratio": missed / (produced + missed) if produced + missed else 0.0,
        "migrations_done": snap.get("migrations_done"), "downtime_ms": snap.get("downtime_ms"),
        "replans": snap.get("replans"), "first_depletion": snap.get("first_depletion"),
        "events": snap.get("events"), "exit_codes": exit_codes or {}, "log_dir": log_dir,
    }


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
