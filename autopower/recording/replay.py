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
                     # every move between nodes: stage-ready notices and committed subgroup rounds
                     # (a subgroup restart's "from" is the unreachable host that ran it before)
      "speed": float | null,                        # mission seconds per wall second (live runs)
      "decisions": int,
      "faults": [{"at_mission_s": float,             # when it was injected, mission seconds
                  "at_wall_unix": float | null,       # ... and on the wall clock (live runs)
                  "kind": str, "target": str,         # target: the parts joined by ","
                  "parts": [str],                     # faults of one kind injected within 0.5 s wall
                                                      # of each other are one fault, e.g. every robot
                                                      # cut from the base station
                  "text": str,
                  "detected_mission_s": float | null, # injection -> seen (each part as the base station
                  "detected_wall_s": float | null,    # saw it, else as any node did; the last part)
                  "reconfigured_mission_s": float | null,  # injection -> the team runs a new
                  "reconfigured_wall_s": float | null,     # configuration (see reconfigured_by)
                  "reconfigured_by": str | null}],    # "subgroup round ID" | "plan epoch N" (every robot
                  # of its network runs it) | "replan" (simulations) | "kept" (simulation: no change)
                  # (no injection recorded: each first liveliness loss is a fault, at its detection,
                  #  detected_* null, reconfigured_* from the detection)
                  # *_wall_s = *_mission_s / the run's speed-up; null in simulations (no wall clock)
      "energy": {"metered_j": float, "model_j": float | null, "error_pct": float | null,
                 "overhead_j": {"migration": float, "recovery": float, "backlog": float,
                                "control": float, "runtime": float},
                 "per_robot": {robot: {"metered_j": float, "model_j": float | null, "error_pct": float | null,
                                       "overhead_j": {"migration": float, "recovery": float, "backlog": float,
                                                      "control": float, "runtime": float},
                                       "control_bytes": {"sent": int, "received": int,  # the control
                                                         "link_sent": int, "link_received": int},  # plane's, of the links'
                                       # CPU seconds on the computer that ran it: the runtime's own
                                       # (charged as overhead "runtime") and its component code's
                                       "cpu_s": {"runtime": float, "component": float},
                                       # outside reconfigurations, and what they shifted (below)
                                       "steady_error_pct": float | null, "transition_j": float | null}},
                 # metered less overheads against the model within reconfiguration windows (from each
                 # change of a robot's model power and each fault, for two status periods of wall
                 # time: recording.transitions) and outside them
                 "transitions": {"window_s": float, "windows": [[float, float]], "covered_s": float,
                                 "transition_j": float | null, "steady_error_pct": float | null,
                                 "steady_model_j": float | null, "steady_metered_j": float | null}},
      "outputs": {"recorded": bool,
                  "produced": int,  # what the sources produced (per run: `produced`, else up to the last delivered)
                  "lost": int,  # produced, not delivered, and in no other class below
                  "duplicated": int, "resent": int, "given_up": int,
                  "held_dropped": int,  # results robots cut off from the sink let go, their hold full
                  "held_dropped_known": bool,  # which seqs (else only counts: then "lost" includes them)
                  "superseded": int,  # a latest-only chain's results a newer one replaced in a hold
                                      # (each with a later output of its run delivered or in hand)
                  "died_with_process": int,  # outputs of a robot's chains that died with its crashed process
                  "unrecorded": int,  # delivered by a sink killed before its recording was flushed
                                      # (named by the restarted sink's journal): not lost, not recorded
                  "in_flight": int,  # a node had them in hand when the team stopped (it says which)
                  "abandoned": int,  # the tail of a run its chain ended by starting a new one (a loss)
                  "chains": {chain: {"outputs": int, "distinct": int, "produced": int, "produced_known": bool,
                                     "lost": int, "duplicated": int,
                                     "held_dropped": int,  # of its missing seqs, dropped by a hold
                                     "superseded": int,  # of its missing seqs, replaced by a newer one
                                     "died_with_process": int,  # of its missing seqs, died in a crash
                                     "unrecorded": int,  # of its missing seqs, delivered (sink journal)
                                     "in_flight": int, "abandoned": int,
                                     "lost_seqs": [[int, int]],  # [run, seq] of the first lost ones
                                                                  # (at most LOST_SEQS_SHOWN)
                                     "runs": [int],
                                     # per run: produced = delivered + unrecorded + held_dropped
                                     #   + superseded + died_with_process + in_flight + abandoned + lost
                                     "by_run": {run: {"produced": int, "produced_known": bool,
                                                      "delivered": int, "duplicated": int, "unrecorded": int,
                                                      "held_dropped": int, "superseded": int,
                                                      "died_with_process": int,
                                                      "in_flight": int, "abandoned": int, "lost": int}}}}},
      "quality": {chain: {metric: float}},          # measured quality, mean over the chain's outputs
                                                    # (blob recall, localisation error; see chains.variants)
      "invariants": [{"name": str, "ok": bool | null, "detail": str}],   # null: not checkable here
      "ok": bool,                                   # every checkable invariant holds
      "lost_outputs": int, "duplicated_outputs": int, "energy_model_error_pct": float | null,
      "energy_steady_error_pct": float | null    # energy.transitions.steady_error_pct
    }

Times are mission seconds (timeline ``mission_time``) unless a key says ``wall``. Energy "model" is the model's power for
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
from autopower.recording import transitions
from autopower.recording.recorder import parse_event
from autopower.recording.telemetry import ALLOCATION, DECISIONS, FAULTS, MESSAGES, MIGRATIONS, Recording, read_recording

# one scalar (the seq) per output of a chain's run: delivered at its sink, or counted apart (`_outputs`)
_APART = ("held_dropped", "superseded", "died_with_process", "sink_journal", "in_flight")
# what a seq not delivered is counted as, by the entity that names it (`_outputs`)
_CLASS_OF = {"sink_journal": "unrecorded", "held_dropped": "held_dropped", "superseded": "superseded",
             "died_with_process": "died_with_process", "in_flight": "in_flight"}
_CLASSES = ("unrecorded", "held_dropped", "superseded", "died_with_process", "in_flight", "abandoned", "lost")
LOST_SEQS_SHOWN = 20  # a chain lists its first lost seqs, so a user (or a failing test) can look them up
_PER_OUTPUT = re.compile(r"^components/(?P<chain>.+)/run/(?P<run>\d+)/(?P<what>seq|produced|" + "|".join(_APART) + ")$")
_SIM_LINK = re.compile(r"link (\S+)[–-](\S+) (cut|healed)")
_SIM_MOVE = re.compile(r"^(?P<stage>\S+): (?P<src>\S+) → (?P<dst>\S+),")
_EPS = 1e-6
GROUP_WINDOW_WALL_S = 0.5  # faults of one kind injected this close together (wall) are one fault


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
    for i, (t, v) in enumerate(zip(times, values, strict=False)):
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
    inside = [v for t, v in zip(ts, vs, strict=False) if t0 - _EPS <= t <= t1 + _EPS and math.isfinite(v)]
    return max(0.0, inside[-1] - inside[0]) if len(inside) >= 2 else 0.0


def _counted(rec: Recording, entity: str, t0: float, t1: float, *, integer: bool = True) -> int | float:
    """What a counter series counted over [t0, t1], across restarts of the process that counts (a
    value below the one before: the counter started again from 0); an int unless not ``integer``."""
    ts, vs = rec.series(entity)
    inside = [v for t, v in zip(ts, vs, strict=False) if t0 - _EPS <= t <= t1 + _EPS and math.isfinite(v)]
    total = sum(b - a if b >= a else b for a, b in zip(inside, inside[1:], strict=False))
    return int(total) if integer else float(total)


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
    # the reconfiguration windows (`transitions`): from every change of a robot's model power and
    # every fault injected or healed, for the time the runtime takes to carry a change out
    model_series = {r: rec.series(f"robots/{r}/model_w") for r in robots}
    window_s = transitions.reaction_s(mission_clock(rec)[0])
    reconfigurations = transitions.windows(
        [t for mt, _ in model_series.values() for t in mt[1:]] + [t for t, _, _ in faults_raw], window_s)
    steady_sum = {"residual_j": 0.0, "model_j": 0.0}
    transition_sum = 0.0
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
        dry = next((t for t, b in zip(ts, bs, strict=False) if b <= _EPS), None)
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
        mt, mv = model_series[r]
        if not mt:
            mt, mv = rec.series(f"robots/{r}/power_w/total")
        model = _integrate_hold(mt, mv, t0, dry if dry is not None else t1) if mt else None
        # what the model's steady state leaves out (migrations, recovery after silent losses) is
        # reported beside it, and the model is checked against the rest
        overhead = {what: _growth(rec, f"robots/{r}/overhead_j/{what}", t0, t1) for what in OVERHEAD_KINDS}
        steady = used - sum(overhead.values())
        shifted, steady_pct = None, None
        if model is not None:
            shifted, model_in = _in_windows(rec, r, ts, bs, mt, mv,
                                            transitions.clip(reconfigurations, t0, dry if dry is not None else t1))
            steady_pct = _pct(steady - shifted - model_in, model - model_in)
            steady_sum["residual_j"] += steady - model - shifted
            steady_sum["model_j"] += model - model_in
            transition_sum += shifted
        per_robot_energy[r] = {"metered_j": used, "model_j": model, "error_pct": _pct(steady, model),
                               "steady_error_pct": steady_pct, "transition_j": shifted,
                               "overhead_j": overhead,
                               "control_bytes": {f"{what}_{way}".removeprefix("control_"):
                                                 _counted(rec, f"robots/{r}/bytes/{what}_{way}", t0, t1)
                                                 for what in ("control", "link") for way in ("sent", "received")},
                               "cpu_s": {what: _counted(rec, f"robots/{r}/cpu_s/{what}", t0, t1, integer=False)
                                         for what in ("runtime", "component")}}
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
    steady_error = _pct(steady_sum["model_j"] + steady_sum["residual_j"], steady_sum["model_j"]) \
        if model_known and robots else None

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
                    f"{sum(c['outputs'] for c in outputs['chains'].values())} outputs" + _apart(outputs))
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
        "speed": mission_clock(rec)[0],
        "decisions": n_decisions,
        "faults": faults,
        "energy": {"metered_j": metered_sum, "model_j": model_sum if model_known else None, "error_pct": error,
                   "overhead_j": overhead_sum, "per_robot": per_robot_energy,
                   "transitions": {"window_s": window_s, "windows": [list(w) for w in reconfigurations],
                                   "covered_s": sum(b - a for a, b in transitions.clip(reconfigurations, start, end)),
                                   "transition_j": transition_sum if model_known and robots else None,
                                   "steady_error_pct": steady_error,
                                   # outside the windows: the model's, and the metered less overheads
                                   "steady_model_j": steady_sum["model_j"] if model_known and robots else None,
                                   "steady_metered_j": steady_sum["model_j"] + steady_sum["residual_j"]
                                   if model_known and robots else None}},
        "outputs": outputs,
        "quality": _quality(rec),
        "invariants": invariants,
        "ok": all(i["ok"] is not False for i in invariants),
        "lost_outputs": outputs["lost"],
        "duplicated_outputs": outputs["duplicated"],
        "energy_model_error_pct": error,
        "energy_steady_error_pct": steady_error,
    }
    return out


def _in_windows(rec: Recording, robot: str, ts: list[float], bs: list[float], mt: list[float], mv: list[float],
                spans: list[tuple[float, float]]) -> tuple[float, float]:
    """(metered energy less overheads less the model's, the model's) of ``robot`` within ``spans``."""
    overheads = [rec.series(f"robots/{robot}/overhead_j/{what}") for what in OVERHEAD_KINDS]
    shifted = model_in = 0.0
    for a, b in spans:
        model = _integrate_hold(mt, mv, a, b) or 0.0
        used = transitions.at(ts, bs, a) - transitions.at(ts, bs, b)
        used -= sum(transitions.at(ot, ov, b) - transitions.at(ot, ov, a) for ot, ov in overheads if ot)
        shifted += used - model
        model_in += model
    return shifted, model_in


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


def mission_clock(rec: Recording) -> tuple[float | None, float | None]:
    """(speed, epoch_unix) of a live run, from its plans; (None, None) for a simulation (no wall clock)."""
    for _, _, p in _events(rec, DECISIONS):
        if p is not None and p.get("type") == "plan" and p.get("speed"):
            epoch = p.get("epoch_unix")
            return float(p["speed"]), (float(epoch) if epoch is not None else None)
    return None, None


def _subgroup_commits(rec: Recording) -> list[tuple[float, str, list[dict]]]:
    """(time, round id, moves) of every committed subgroup round (robots agreeing without the base)."""
    proposals: dict[str, list[dict]] = {}
    out = []
    # rounds are protocol messages (events/messages); recordings made before they moved there
    # logged them with the decisions
    for t, _text, p in sorted(_events(rec, DECISIONS) + _events(rec, MESSAGES), key=lambda e: e[0]):
        if p is None:
            continue
        if p.get("type") == "sg-propose":
            proposals[str(p.get("round_id"))] = list(p.get("moves") or [])
        elif p.get("type") == "sg-decision" and p.get("commit"):
            round_id = str(p.get("round_id"))
            if all(r != round_id for _, r, _ in out):  # every member may announce it; count it once
                out.append((t, round_id, proposals.get(round_id, [])))
    return out


def _migrations(rec: Recording) -> list[dict[str, Any]]:
    """Every move of a stage between nodes, with its real source and destination.

    Moves come from stage-ready notices (live: the new host runs it), from committed subgroup
    rounds (live: robots restart or move stages without the base station; a restart's source is
    the host that ran the stage before, out of reach) and from a simulation's migration texts.
    """
    out = []
    host: dict[str, str] = {}
    timeline = [(t, "ready", text, p) for t, text, p in _events(rec, MIGRATIONS)]
    timeline += [(t, "subgroup", round_id, moves) for t, round_id, moves in _subgroup_commits(rec)]
    timeline.sort(key=lambda e: e[0])
    for t, what, text, p in timeline:
        if what == "subgroup":
            for move in p:
                stage, dst = move.get("stage"), move.get("to_node")
                src = move.get("from_node") or host.get(stage)
                how = "moved" if move.get("from_node") else "restarted"
                host[stage] = dst
                if src != dst:
                    out.append({"t_s": t, "stage": stage, "from": src, "to": dst, "downtime_ms": None,
                                "text": f"{how} by subgroup round {text}"})
            continue
        if p is not None and p.get("type") == "stage-ready":
            stage, node = p.get("stage"), p.get("node")
            before = host.get(stage)
            host[stage] = node
            # a move: to another node, or state imported from a host this recording never saw
            if (before is not None and before != node) or (before is None and p.get("imported_state")):
                out.append({"t_s": t, "stage": stage, "from": before, "to": node,
                            "downtime_ms": p.get("downtime_ms"), "text": text})
            continue
        if p is not None:  # control traffic (assign, migrate-out, ...): context for the viewer
            continue
        m = _SIM_MOVE.match(text)
        out.append({"t_s": t, "stage": m["stage"] if m else None, "from": m["src"] if m else None,
                    "to": m["dst"] if m else None, "downtime_ms": None, "text": text})
    return out


def _plans(rec: Recording) -> list[tuple[float, int, list[str]]]:
    """(time, epoch, robots of its network) of each live plan, first publication only."""
    seen: dict[int, tuple[float, list[str]]] = {}
    for t, _text, p in _events(rec, DECISIONS):
        if p is not None and p.get("type") == "plan":
            epoch = int(p.get("epoch", -1))
            if epoch not in seen:
                nodes = {x for link in p.get("links") or [] for x in link[:2]} | set((p.get("placement") or {}).values())
                seen[epoch] = (t, sorted(nodes))
    return sorted((t, epoch, nodes) for epoch, (t, nodes) in seen.items())


def _all_run_epoch(rec: Recording, robots: list[str], epoch: int, t_from: float) -> float | None:
    """When the last of `robots` reported running plan `epoch` (or later); None if one never did."""
    latest = t_from
    for robot in robots:
        ts, vs = rec.series(f"robots/{robot}/plan_epoch")
        if not ts:
            continue  # not a robot, or its statuses were not recorded
        t = next((t for t, v in zip(ts, vs, strict=False) if v >= epoch and t >= t_from - 1.0), None)
        if t is None:
            return None
        latest = max(latest, t)
    return latest


def _group(injected: list[dict], window_s: float) -> list[dict]:
    """Faults of one kind injected within `window_s` (mission seconds) of each other are one fault."""
    groups: list[dict] = []
    for fault in sorted(injected, key=lambda f: f["t_s"]):
        last = groups[-1] if groups else None
        if (last is not None and not fault.get("_from_detection") and last["kind"] == fault["kind"]
                and fault["t_s"] - last["_last_t"] <= window_s):
            last["parts"].append(fault["target"])
            last["text"] += "; " + fault["text"]
            last["_last_t"] = fault["t_s"]
            continue
        groups.append({**fault, "parts": [fault["target"]], "_last_t": fault["t_s"]})
    for g in groups:
        g["target"] = ",".join(g["parts"])
        del g["_last_t"]
    return groups


def _faults(rec: Recording, kind: str, raw, decision_times: list[float], migrations) -> list[dict[str, Any]]:
    speed, epoch_unix = mission_clock(rec)
    base = rec.properties.get("basestation")
    injected, detected = [], []
    for t, text, p in raw:
        if p is not None and p.get("type") == "fault":
            phase = p.get("phase")
            if phase == "injected":
                injected.append({"t_s": t, "kind": p.get("kind", "fault"), "target": p.get("target", ""),
                                 "text": text})
            elif phase == "detected":
                detected.append((t, p.get("target", ""), p.get("observer")))
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
        for t, target, observer in detected:
            if target not in seen:
                seen.add(target)
                injected.append({"t_s": t, "kind": "node-lost", "target": target,
                                 "text": f"{observer} lost {target}", "_from_detection": True})
    # injected together (one command per link, a few ms apart in wall time) = one fault
    faults = _group(injected, GROUP_WINDOW_WALL_S * speed if speed else _EPS)
    stage_ready = sorted(m["t_s"] for m in migrations)
    plans = _plans(rec)
    commits = _subgroup_commits(rec)
    out = []
    for i, fault in enumerate(faults):
        t_f = fault["t_s"]
        t_next = min((f["t_s"] for f in faults[i + 1:] if f["t_s"] > t_f + _EPS), default=math.inf)
        if fault.pop("_from_detection", False):
            t_first_seen, det = t_f, None  # injection time unknown
        else:
            seen = _detection(fault["parts"], detected, t_f, t_next, base)
            if seen is None and kind == "simulation":
                seen = (t_f, t_f)  # the simulator reacts to events the moment they happen
            t_first_seen = None if seen is None else seen[0]
            det = None if seen is None else max(0.0, seen[1] - t_f)
        # The team may act on the first part it sees (a subgroup round commits once its members lost
        # the base station, whatever a third robot has yet to notice): the reaction is searched from
        # the first part seen, while the fault counts as detected when its last part is; for a fault
        # no liveliness shows (a radio change), from its injection.
        t_ref = t_f if t_first_seen is None else t_first_seen
        gone = set(fault["parts"]) if fault["kind"] == "crash-agent" else set()
        reconf, how = _reconfiguration(rec, kind, t_ref, t_next, plans, commits, decision_times, stage_ready, gone)
        if reconf is None and kind == "simulation" and not [t for t in decision_times if t_ref - _EPS <= t < t_next - _EPS]:
            reconf, how = t_ref, "kept"  # the policy was asked at once and kept the configuration
        reconf_s = None if reconf is None else max(0.0, reconf - t_f)
        out.append({
            "at_mission_s": t_f,
            "at_wall_unix": (epoch_unix + t_f / speed) if (speed and epoch_unix is not None) else None,
            "kind": fault["kind"], "target": fault["target"], "parts": fault["parts"], "text": fault["text"],
            "detected_mission_s": det, "reconfigured_mission_s": reconf_s,
            "detected_wall_s": (det / speed) if (det is not None and speed) else None,
            "reconfigured_wall_s": (reconf_s / speed) if (reconf_s is not None and speed) else None,
            "reconfigured_by": how,
        })
    return out


def _detection(parts: list[str], detected, t_f: float, t_next: float,
               base: str | None) -> tuple[float, float] | None:
    """(first, last): when the first and the last part of a fault were seen. A link is seen when
    either of its ends first saw it (the team acts on the first report: the base station replans
    from a robot's relayed status before its own liveliness lease runs out), a node when the base
    station saw it (else when any node did). None if no part was seen."""
    seen = []
    for target in parts:
        names = set(target.split("-")) if target else set()
        hits = [(t, observer) for t, who, observer in detected
                if t_f - _EPS <= t < t_next and (not names or who in names)]
        if hits:
            by_end = [t for t, observer in hits if len(names) > 1 and observer in names]
            by_base = [t for t, observer in hits if observer == base]
            seen.append(min(by_end or by_base or [t for t, _ in hits]))
    return (min(seen), max(seen)) if seen else None


def _reconfiguration(rec, kind, t_ref, t_next, plans, commits, decision_times, stage_ready, gone=frozenset()):
    """(time, how) the team ran a new configuration after a fault seen at t_ref; (None, None) if never.

    A subgroup round committed in the window wins (the robots reallocated without the base
    station); else the base station's first plan after the fault, once every robot of its network
    reports running it (statuses), or, in recordings without those, once its moved stages run.
    ``gone``: the robots the fault killed. A plan whose network still has one was made before the
    base station knew (the links to a killed robot can be reported down a moment before the
    robot): the first plan without them is the one the team runs without them. Waiting for the
    killed robot to run the earlier one would count its restart as reconfiguration time.
    """
    for t, round_id, _moves in commits:
        if t_ref - _EPS <= t < t_next:
            return t, f"subgroup round {round_id}"
    live_plans = [(t, epoch, nodes) for t, epoch, nodes in plans if t_ref - _EPS <= t < t_next - _EPS]
    if gone:
        live_plans = [p for p in live_plans if not gone & set(p[2])] or live_plans
    if live_plans:
        t_plan, epoch, nodes = live_plans[0]
        robots = [n for n in nodes if n != rec.properties.get("basestation")]
        if any(rec.series(f"robots/{r}/plan_epoch")[0] for r in robots):
            t_run = _all_run_epoch(rec, robots, epoch, t_plan)
            return (t_run, f"plan epoch {epoch}") if t_run is not None else (None, None)
    replans = [t for t in decision_times if t_ref - _EPS <= t < t_next - _EPS]
    if not replans:
        return None, None
    t_plan = replans[0]
    later = [t for t in decision_times if t > t_plan + _EPS]
    horizon = min(t_next, later[0] if later else math.inf)
    landed = [t for t in stage_ready if t_plan - _EPS <= t < horizon]
    return max([t_plan, *landed]), "replan"


_QUALITY = re.compile(r"^components/(?P<chain>.+)/quality/(?P<metric>[^/]+)$")


def _quality(rec: Recording) -> dict[str, dict[str, float]]:
    """Each chain's measured quality (`recording.live.QualityScorer`), the mean over its outputs;
    blob recall is pooled over every camera frame (victims found / victims in view)."""
    out: dict[str, dict[str, float]] = {}
    for entity, (_, values) in rec.scalars.items():
        m = _QUALITY.match(entity)
        finite = [v for v in values if math.isfinite(v)] if m else []
        if finite:
            out.setdefault(m["chain"], {})[m["metric"]] = sum(finite) / len(finite)
    for _chain, q in out.items():
        if "victims_total" in q and q["victims_total"] > 0:
            q["recall"] = q.get("victims_found", 0.0) / q["victims_total"]
    return out


def _apart(outputs: dict[str, Any]) -> str:
    """What the exactly-once detail counts apart from lost outputs: by design, and a crash's cost."""
    parts = []
    if outputs["held_dropped"]:
        parts.append(f"{outputs['held_dropped']} dropped by robots cut off from their sink, their hold full"
                     + (": by design" if outputs["held_dropped_known"] else ""))
    if outputs.get("superseded"):
        parts.append(f"{outputs['superseded']} of latest-only chains replaced in a hold by a newer one "
                     "(delivered, or in hand at the stop)")
    if outputs.get("died_with_process"):
        parts.append(f"{outputs['died_with_process']} of a robot's chains that died with its crashed process, "
                     "in its memory only")
    if outputs.get("in_flight"):
        parts.append(f"{outputs['in_flight']} still in flight when the team stopped (a node had them in hand)")
    if outputs.get("abandoned"):
        parts.append(f"{outputs['abandoned']} abandoned when their chain restarted in a new run (the old run's "
                     "tail: a loss, see docs/known-limits.md)")
    if outputs.get("unrecorded"):
        parts.append(f"{outputs['unrecorded']} delivered by a sink killed before it flushed their recording "
                     "(named by its journal)")
    if not parts:
        return ""
    return (" (besides " if outputs["held_dropped_known"] or not outputs["held_dropped"] else " (") \
        + "; and ".join(parts) + ")"


def _outputs(rec: Recording) -> dict[str, Any]:
    """Outputs per chain and run: produced, delivered (once, twice), and each one not delivered in
    exactly one class, so that produced = distinct + unrecorded + held_dropped + superseded
    + in_flight + died_with_process + abandoned + lost, for every run, tails included.

    *Produced* is what the chain's source says it produced in the run (``.../run/<run>/produced``,
    logged at a clean stop, `Recorder.record_stop`); without it (its robot killed for good, an older
    recording) the run counts up to the highest seq delivered, and ``produced_known`` says so. A
    seq not delivered is, in this order:
    - *unrecorded*: delivered by a sink killed before it flushed its recording (named by the
      restarted sink's journal, ``.../sink_journal``);
    - *held_dropped*: let go by a robot cut off from the sink, its hold full (``.../held_dropped``,
      logged by that robot as it dropped it): by design, within the budget;
    - *superseded*: a latest-only chain's result (``keep = "latest"``) a robot cut off from the
      sink let go when a newer one of the run replaced it in its hold (``.../superseded``), and
      only if a later output of the run was delivered or is named in flight: the newer one did
      what it was let go for. Without that evidence the seq falls through to the classes below;
    - *in_flight*: a node still had it in hand when the team stopped (``.../in_flight``, logged by
      that node at its clean stop: custody, hold, a stage's gate or worker);
    - *died_with_process*: an output of a chain sourced on a robot, in its crashed process's memory
      only (``.../died_with_process``, named by the restarted process: `Resuming._died_with_process`
      and `_died_in_hand`), that no node names in flight (a frame some node still held did not die);
    - *abandoned*: after the last output its run delivered, in a run its chain ended by starting a
      new one (a later run of the chain is recorded): what the old run still held upstream was
      obsolete from then on (docs/known-limits.md). A loss, counted apart so it is not hidden in
      the tail of a run;
    - *lost*: none of the above."""
    seqs_of: dict[tuple[str, int], list[int]] = {}
    apart_of: dict[str, dict[tuple[str, int], set[int]]] = {what: {} for what in _APART}
    produced_of: dict[tuple[str, int], int] = {}
    for entity, (_, values) in rec.scalars.items():
        m = _PER_OUTPUT.match(entity)
        if not m:
            continue
        finite = [int(v) for v in values if math.isfinite(v)]
        key = (m["chain"], int(m["run"]))
        what = m["what"]
        if what == "seq":
            seqs_of.setdefault(key, []).extend(finite)
        elif what == "produced":
            produced_of[key] = max([produced_of.get(key, 0), *finite])
        else:
            apart_of[what].setdefault(key, set()).update(finite)
    dropped_of = apart_of["held_dropped"]
    last_run: dict[str, int] = {}
    for chain, run in (*seqs_of, *produced_of):
        last_run[chain] = max(run, last_run.get(chain, run))
    chains: dict[str, Any] = {}
    totals = dict.fromkeys(_CLASSES, 0)
    totals["duplicated"] = 0
    for chain, run in sorted({*seqs_of, *produced_of}):
        seqs = seqs_of.get((chain, run), [])
        c = chains.setdefault(chain, {"outputs": 0, "distinct": 0, "produced": 0, "produced_known": True,
                                      **dict.fromkeys(_CLASSES, 0), "duplicated": 0, "lost_seqs": [],
                                      "runs": [], "by_run": {}})
        distinct = set(seqs)
        after_last = max(distinct, default=-1)  # the tail starts past the last output delivered
        produced = max(produced_of.get((chain, run), 0), after_last + 1)
        missing = set(range(produced)) - distinct
        classes: dict[str, set[int]] = {}
        # in this order: a node that names a frame in hand at its stop shows it did not die with
        # a crashed process, whatever the restarted one guessed from its window
        newest_kept = max([after_last, *apart_of["in_flight"].get((chain, run), ())])
        for what in ("sink_journal", "held_dropped", "superseded", "in_flight", "died_with_process"):
            named = missing & apart_of[what].get((chain, run), set())
            if what == "superseded":  # the evidence: a later output of the run reached the sink or is in hand
                named = {seq for seq in named if seq < newest_kept}
            classes[_CLASS_OF[what]] = named
            missing -= named
        classes["abandoned"] = {s for s in missing if s > after_last} if run < last_run[chain] else set()
        lost = missing - classes["abandoned"]
        if lost and len(c["lost_seqs"]) < LOST_SEQS_SHOWN:
            c["lost_seqs"].extend([run, seq] for seq in sorted(lost)[:LOST_SEQS_SHOWN - len(c["lost_seqs"])])
        by_run = {"produced": produced, "produced_known": (chain, run) in produced_of, "delivered": len(distinct),
                  "duplicated": len(seqs) - len(distinct), **{k: len(v) for k, v in classes.items()},
                  "lost": len(lost)}
        c["by_run"][str(run)] = by_run
        c["outputs"] += len(seqs)
        c["distinct"] += len(distinct)
        c["produced"] += produced
        c["produced_known"] = c["produced_known"] and by_run["produced_known"]
        c["duplicated"] += by_run["duplicated"]
        totals["duplicated"] += by_run["duplicated"]
        for what in _CLASSES:
            c[what] += by_run[what]
            totals[what] += by_run[what]
        c["runs"].append(run)
    custody = {what: sum(_counter_total(times, values) for e, (times, values) in rec.scalars.items()
                         if e.startswith("custody/") and e.endswith(f"/{what}"))
               for what in ("resent", "evicted", "held_dropped")}
    # a seq logged as let go that reached the sink all the same is no drop (a restarted robot logs
    # again every result its journal had past what it takes back, acknowledged ones included)
    held = (sum(len(d - set(seqs_of.get(k, ())) - apart_of["sink_journal"].get(k, set()))
                for k, d in dropped_of.items()) if dropped_of
            else int(custody["held_dropped"]))
    return {"recorded": bool(seqs_of), "lost": totals["lost"], "duplicated": totals["duplicated"],
            "resent": int(custody["resent"]), "given_up": int(custody["evicted"]),
            "held_dropped": held, "held_dropped_known": bool(dropped_of), "superseded": totals["superseded"],
            "died_with_process": totals["died_with_process"], "unrecorded": totals["unrecorded"],
            "in_flight": totals["in_flight"], "abandoned": totals["abandoned"],
            "produced": sum(c["produced"] for c in chains.values()),
            "chains": dict(sorted(chains.items()))}


def _counter_total(times, values) -> float:
    """What a node's counter counted over the whole run. A restarted process counts from 0 again
    on the same entity, so each fall starts a new count (the last value alone was the restarted
    process's share only)."""
    total = last = 0.0
    for _, value in sorted(zip(times, values, strict=False)):
        if not math.isfinite(value):
            continue
        if value < last:
            total += last
        last = value
    return total + last


