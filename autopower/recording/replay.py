"""Replay an AutoPower recording: what happened, whether the invariants held, what else could have.

`summarize(recording)` reads a recording written by the simulator (``autopower simulate
--record``) or by a live run (`autopower.recording.recorder`, merged ``run.rrd``) and derives everything
from the telemetry layout and the structured text events (`autopower.recording.recorder.parse_event`).
`what_if(recording, ...)` replans offline from the recorded state at a chosen time.

``autopower replay RUN.rrd --json`` prints one object::

    {
      "recording": str, "recording_id": str | null, "kind": "simulation" | "live",
      "scenario": str | null, "policy": str | null, "accounting": str | null, "topology": str | null,
      "mission": {"start_s": float, "end_s": float, "covered_s": float},
      "robots": {robot: {"initial_j": float, "final_j": float, "used_j": float, "min_j": float,
                         "power_w": float | null,          # mean metered power over the recording
                         "ran_dry_at_s": float | null,     # battery reached 0
                         "lifetime_s": float | null}},     # ran_dry_at_s, else end + final_j / power_w (projected)
      "first_dry": {"robot": str, "at_s": float, "projected": bool} | null,
      "migrations": {"count": int, "downtime_ms_total": float | null, "downtime_ms_max": float | null,
                     "list": [{"t_s": float, "stage": str, "from": str | null, "to": str | null,
                               "downtime_ms": float | null, "text": str}]},
      "decisions": int,
      "faults": [{"t_s": float, "kind": str, "target": str, "text": str,
                  "detected_s": float | null,       # injection -> first detection (s, mission time)
                  "reconfigured_s": float | null}], # injection -> last stage running after the replan
                  # (no injection recorded: each first liveliness loss is a fault, t_s its detection,
                  #  detected_s null, reconfigured_s from the detection)
      "energy": {"metered_j": float, "model_j": float | null, "error_pct": float | null,
                 "overhead_j": {"migration": float, "recovery": float},
                 "per_robot": {robot: {"metered_j": float, "model_j": float | null, "error_pct": float | null,
                                       "overhead_j": {"migration": float, "recovery": float}}}},
      "outputs": {"recorded": bool, "lost": int, "duplicated": int, "resent": int, "given_up": int,
                  "chains": {chain: {"outputs": int, "distinct": int, "lost": int, "duplicated": int,
                                     "runs": [int]}}},
      "invariants": [{"name": str, "ok": bool | null, "detail": str}],   # null: not checkable here
      "ok": bool,                                   # every checkable invariant holds
      "lost_outputs": int, "duplicated_outputs": int, "energy_model_error_pct": float | null
    }

Times are mission seconds (timeline ``mission_time``). Energy "model" is the model's power for
the recorded allocation and network (live: ``robots/<r>/model_w`` from each plan; simulation:
``robots/<r>/power_w/total``, which is the model) integrated over the recorded interval;
"metered" is the battery drop actually recorded; error = (metered - overheads - model) / model,
where the overheads are the energy the model's steady state leaves out by design (migrations'
state on the radios, recovery after silent losses: ``robots/<r>/overhead_j/...``), reported
beside it.
With ``--what-if`` the object gains ``"what_if"`` (see `what_if`).
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path
from typing import Any

from autopower.errors import RecordingError
from autopower.model.parts import OVERHEAD_KINDS
from autopower.recording.recorder import parse_event
from autopower.recording.telemetry import ALLOCATION, DECISIONS, FAULTS, MIGRATIONS, Recording, read_recording

_OUTPUT = re.compile(r"^components/(?P<chain>.+)/run/(?P<run>\d+)/seq$")
_SIM_LINK = re.compile(r"link (\S+)[–-](\S+) (cut|healed)")
_SIM_MOVE = re.compile(r"^(?P<stage>\S+): (?P<src>\S+) → (?P<dst>\S+),")
_EPS = 1e-6


def load(path: str | Path) -> Recording:
    """Read a recording; `RecordingError` (what, which file, what to do) for anything unusable."""
    path = Path(path)
    hint = "; pass the run.rrd written by 'autopower simulate --record' or a live run"
    if path.is_file() and path.stat().st_size == 0:
        raise RecordingError(f"{path}: the file is empty (the run may have crashed before writing){hint}")
    try:
        with warnings.catch_warnings():  # a truncated file makes the reader warn before it fails
            warnings.simplefilter("ignore")
            rec = read_recording(path)
    except RecordingError as exc:
        raise RecordingError(f"{exc}{hint}") from None
    except Exception as exc:  # noqa: BLE001 - any other failure of the reader is a bad file too
        raise RecordingError(f"{path}: cannot read the recording ({type(exc).__name__}: {exc}){hint}") from None
    if not any(e.endswith("/battery_j") for e in rec.scalars):
        raise RecordingError(f"{path}: an AutoPower recording with no battery data (truncated, or the run "
                             f"ended before its first status){hint}")
    return rec


def replay_summary(path: str | Path) -> dict[str, Any]:
    """`load` + `summarize`: the ``--json`` object of ``autopower replay PATH`` (for the demo)."""
    return summarize(load(path), path)


# ---------------------------------------------------------------------------------------------
# helpers over the recording
# ---------------------------------------------------------------------------------------------


def _robots(rec: Recording) -> list[str]:
    return sorted(e.split("/")[1] for e in rec.scalars if e.startswith("robots/") and e.endswith("/battery_j"))


def _events(rec: Recording, entity: str) -> list[tuple[float, str, dict | None]]:
    out = []
    for t, line, _level in rec.log(entity):
        text, payload = parse_event(line)
        out.append((t, text, payload))
    return out


def _integrate_hold(times: list[float], values: list[float], t0: float, t1: float) -> float | None:
    """Integral over [t0, t1] of a step function holding each value until the next sample."""
    if not times or t1 <= t0:
        return None if not times else 0.0
    total = 0.0
    for i, (t, v) in enumerate(zip(times, values)):
        nxt = times[i + 1] if i + 1 < len(times) else t1
        a, b = max(t, t0), min(nxt, t1)
        if b > a and math.isfinite(v):
            total += v * (b - a)
    if times[0] > t0:  # before the first value: assume the first value (the plan in force at start)
        total += values[0] * (min(times[0], t1) - t0)
    return total


def _growth(rec: Recording, entity: str, t0: float, t1: float) -> float:
    """How much a cumulative series grew over [t0, t1] (0 if it was not recorded)."""
    ts, vs = rec.series(entity)
    inside = [v for t, v in zip(ts, vs) if t0 - _EPS <= t <= t1 + _EPS and math.isfinite(v)]
    return max(0.0, inside[-1] - inside[0]) if len(inside) >= 2 else 0.0


def _pct(measured: float, model: float | None) -> float | None:
    if model is None or abs(model) < 1e-12:
        return None
    return (measured - model) / model * 100.0


# ---------------------------------------------------------------------------------------------
# summary
# ---------------------------------------------------------------------------------------------


def summarize(rec: Recording, path: str | Path | None = None) -> dict[str, Any]:
    props = rec.properties
    kind = props.get("kind") or "simulation"
    robots = _robots(rec)
    all_t = [t for e, (ts, _) in rec.scalars.items() if e.startswith("robots/") for t in ts]
    start, end = (min(all_t), max(all_t)) if all_t else (0.0, 0.0)

    faults_raw = _events(rec, FAULTS)
    energy_bumps = {round(t, 6) for t, text, p in faults_raw
                    if p is None and ("battery" in text or "energy" in text)}

    # ---- robots and energy
    robot_out: dict[str, Any] = {}
    per_robot_energy: dict[str, Any] = {}
    increases: list[str] = []
    metered_sum = model_sum = 0.0
    overhead_sum = {what: 0.0 for what in OVERHEAD_KINDS}
    model_known = True
    for r in robots:
        ts, bs = rec.series(f"robots/{r}/battery_j")
        if not ts:
            continue
        t0, t1 = ts[0], ts[-1]
        dry = next((t for t, b in zip(ts, bs) if b <= _EPS), None)
        for i in range(1, len(bs)):
            if bs[i] > bs[i - 1] + max(1e-6, 1e-9 * abs(bs[i - 1])) and round(ts[i], 6) not in energy_bumps:
                increases.append(f"{r} at {ts[i]:.1f} s: {bs[i - 1]:.3f} → {bs[i]:.3f} J")
        gained = sum(max(0.0, bs[i] - bs[i - 1]) for i in range(1, len(bs)))
        used = bs[0] - bs[-1] + gained
        power = used / (t1 - t0) if t1 > t0 else None
        if dry is not None:
            life, projected = dry, False
        elif power and power > 0:
            life, projected = t1 + bs[-1] / power, True
        else:
            life, projected = None, True
        robot_out[r] = {"initial_j": bs[0], "final_j": bs[-1], "used_j": used, "min_j": min(bs),
                        "power_w": power, "ran_dry_at_s": dry, "lifetime_s": life, "_projected": projected}
        mt, mv = rec.series(f"robots/{r}/model_w")
        if not mt:
            mt, mv = rec.series(f"robots/{r}/power_w/total")
        model = _integrate_hold(mt, mv, t0, dry if dry is not None else t1) if mt else None
        # what the model's steady state leaves out (migrations, recovery after silent losses) is
        # reported beside it, and the model is checked against the rest
        overhead = {what: _growth(rec, f"robots/{r}/overhead_j/{what}", t0, t1) for what in OVERHEAD_KINDS}
        steady = used - sum(overhead.values())
        per_robot_energy[r] = {"metered_j": used, "model_j": model, "error_pct": _pct(steady, model),
                               "overhead_j": overhead}
        for what, joules in overhead.items():
            overhead_sum[what] += joules
        metered_sum += used
        if model is None:
            model_known = False
        else:
            model_sum += model
    first = None
    candidates = [(v["lifetime_s"], r) for r, v in robot_out.items() if v["lifetime_s"] is not None]
    if candidates:
        life, r = min(candidates)
        first = {"robot": r, "at_s": life, "projected": robot_out[r]["_projected"]}
    for v in robot_out.values():
        v.pop("_projected")
    error = _pct(metered_sum - sum(overhead_sum.values()), model_sum) if model_known and robots else None

    # ---- decisions, migrations, faults
    decision_times, n_decisions = _decisions(rec)
    migrations = _migrations(rec)
    faults = _faults(rec, kind, faults_raw, decision_times, migrations)

    # ---- outputs
    outputs = _outputs(rec)
    sink_dups = [v for e, (ts, vs) in rec.scalars.items() if e.endswith("/sink/duplicates_total") for v in vs]

    invariants = [
        {"name": "battery never increases", "ok": not increases,
         "detail": "; ".join(increases[:5]) or f"{len(robots)} robot(s) checked"},
        {"name": "every output exactly once at its sink",
         "ok": (outputs["lost"] == 0 and outputs["duplicated"] == 0) if outputs["recorded"] else None,
         "detail": (f"{outputs['lost']} lost, {outputs['duplicated']} duplicated over "
                    f"{sum(c['outputs'] for c in outputs['chains'].values())} outputs")
         if outputs["recorded"] else "no component outputs in this recording (simulations model, not run, them)"},
        {"name": "sinks counted no duplicate", "ok": (max(sink_dups) == 0) if sink_dups else None,
         "detail": f"max duplicates_total {max(sink_dups):.0f}" if sink_dups else "no sink counters recorded"},
        {"name": "mission time covered", "ok": end > start, "detail": f"{start:.1f} s to {end:.1f} s"},
        {"name": "migrations completed (downtime recorded, finite)",
         "ok": all(m["downtime_ms"] is None or (math.isfinite(m["downtime_ms"]) and m["downtime_ms"] >= 0)
                   for m in migrations),
         "detail": f"{len(migrations)} migration(s)"},
    ]
    downtimes = [m["downtime_ms"] for m in migrations if m["downtime_ms"] is not None]
    out = {
        "recording": str(path) if path is not None else None,
        "recording_id": props.get("recording_id"),
        "kind": kind,
        "scenario": props.get("scenario"),
        "policy": props.get("policy") or _live_policy(rec),
        "accounting": props.get("accounting"),
        "topology": props.get("topology"),
        "mission": {"start_s": start, "end_s": end, "covered_s": end - start},
        "robots": robot_out,
        "first_dry": first,
        "migrations": {"count": len(migrations),
                       "downtime_ms_total": sum(downtimes) if downtimes else None,
                       "downtime_ms_max": max(downtimes) if downtimes else None,
                       "list": migrations},
        "decisions": n_decisions,
        "faults": faults,
        "energy": {"metered_j": metered_sum, "model_j": model_sum if model_known else None, "error_pct": error,
                   "overhead_j": overhead_sum, "per_robot": per_robot_energy},
        "outputs": outputs,
        "invariants": invariants,
        "ok": all(i["ok"] is not False for i in invariants),
        "lost_outputs": outputs["lost"],
        "duplicated_outputs": outputs["duplicated"],
        "energy_model_error_pct": error,
    }
    return out


def _live_policy(rec: Recording) -> str | None:
    """The policy a live base station decided with (its plans name it)."""
    names = [p.get("policy") for _, _, p in _events(rec, DECISIONS) if p is not None and p.get("type") == "plan"]
    return next((n for n in names if n), None)


def _decisions(rec: Recording) -> tuple[list[float], int]:
    """Times at which the team was replanned, and how many decisions the recording holds."""
    events = _events(rec, DECISIONS)
    epochs: dict[int, float] = {}
    plain: set[float] = set()
    for t, _text, p in events:
        if p is not None and p.get("type") == "plan":
            epochs.setdefault(int(p.get("epoch", -1)), t)
        elif p is None:
            plain.add(t)
    if not epochs:  # a simulation: the allocation graph changes at each decision
        times = sorted({t for t, *_ in rec.graphs.get(ALLOCATION, [])} | plain)
        return times, len({t for t, *_ in rec.graphs.get(ALLOCATION, [])}) or len(plain)
    return sorted(epochs.values()), len(epochs)


def _migrations(rec: Recording) -> list[dict[str, Any]]:
    out = []
    host: dict[str, str] = {}
    for t, text, p in _events(rec, MIGRATIONS):
        if p is not None and p.get("type") == "stage-ready":
            stage, node = p.get("stage"), p.get("node")
            before = host.get(stage)
            host[stage] = node
            if p.get("imported_state") or (before is not None and before != node):
                out.append({"t_s": t, "stage": stage, "from": before, "to": node,
                            "downtime_ms": p.get("downtime_ms"), "text": text})
            continue
        if p is not None:  # control traffic (assign, migrate-out, ...): context for the viewer
            continue
        m = _SIM_MOVE.match(text)
        out.append({"t_s": t, "stage": m["stage"] if m else None, "from": m["src"] if m else None,
                    "to": m["dst"] if m else None, "downtime_ms": None, "text": text})
    return out


def _faults(rec: Recording, kind: str, raw, decision_times: list[float], migrations) -> list[dict[str, Any]]:
    injected, detected = [], []
    for t, text, p in raw:
        if p is not None and p.get("type") == "fault":
            phase = p.get("phase")
            if phase == "injected":
                injected.append({"t_s": t, "kind": p.get("kind", "fault"), "target": p.get("target", ""),
                                 "text": text})
            elif phase == "detected":
                detected.append((t, p.get("target", ""), text))
            continue
        if p is None:
            m = _SIM_LINK.search(text)
            if m and m[3] == "healed":
                continue
            if "repaired" in text or "joined" in text or "enabled" in text:
                continue
            injected.append({"t_s": t, "kind": "cut" if m else "event",
                             "target": f"{m[1]}-{m[2]}" if m else "", "text": text})
    if not injected:  # a live run without a fault tool: each first detection is a fault
        seen = set()
        for t, target, text in detected:
            if target not in seen:
                seen.add(target)
                injected.append({"t_s": t, "kind": "node-lost", "target": target, "text": text, "_from_detection": True})
    injected.sort(key=lambda f: f["t_s"])
    stage_ready = sorted(m["t_s"] for m in migrations)
    for i, fault in enumerate(injected):
        t_f = fault["t_s"]
        t_next = min((f["t_s"] for f in injected[i + 1:] if f["t_s"] > t_f + _EPS), default=math.inf)
        names = set(fault["target"].split("-")) if fault["target"] else set()
        if fault.pop("_from_detection", False):
            t_det = t_f
            fault["detected_s"] = None  # injection time unknown
        else:
            hits = [t for t, target, _ in detected if t_f - _EPS <= t < t_next and (not names or target in names)]
            if hits:
                t_det = min(hits)
            elif kind == "simulation":
                t_det = t_f  # the simulator reacts to events the moment they happen
            else:
                t_det = None
            fault["detected_s"] = None if t_det is None else max(0.0, t_det - t_f)
        fault["reconfigured_s"] = None
        if t_det is None:  # not seen by liveliness (a radio fault): the replan tells when it was handled
            t_det = t_f
        replans = [t for t in decision_times if t_det - _EPS <= t < t_next - _EPS]
        if not replans:
            if kind == "simulation":  # the policy was asked at once and kept the configuration
                fault["reconfigured_s"] = fault["detected_s"]
            continue
        t_plan = replans[0]
        later = [t for t in decision_times if t > t_plan + _EPS]
        horizon = min(t_next, later[0] if later else math.inf)
        landed = [t for t in stage_ready if t_plan - _EPS <= t < horizon]
        fault["reconfigured_s"] = max(0.0, max([t_plan, *landed]) - t_f)
    return injected


def _outputs(rec: Recording) -> dict[str, Any]:
    chains: dict[str, Any] = {}
    lost_all = dup_all = 0
    for entity, (_, values) in rec.scalars.items():
        m = _OUTPUT.match(entity)
        if not m:
            continue
        chain, run = m["chain"], int(m["run"])
        c = chains.setdefault(chain, {"outputs": 0, "distinct": 0, "lost": 0, "duplicated": 0, "runs": []})
        seqs = [int(v) for v in values if math.isfinite(v)]
        distinct = set(seqs)
        lost = (max(distinct) + 1 - len(distinct)) if distinct else 0
        dup = len(seqs) - len(distinct)
        c["outputs"] += len(seqs)
        c["distinct"] += len(distinct)
        c["lost"] += lost
        c["duplicated"] += dup
        c["runs"].append(run)
        lost_all += lost
        dup_all += dup
    for c in chains.values():
        c["runs"].sort()
    custody = {what: sum(values[-1] for e, (_, values) in rec.scalars.items()
                         if e.startswith("custody/") and e.endswith(f"/{what}") and values)
               for what in ("resent", "evicted")}
    return {"recorded": bool(chains), "lost": lost_all, "duplicated": dup_all,
            "resent": int(custody["resent"]), "given_up": int(custody["evicted"]),
            "chains": dict(sorted(chains.items()))}


