"""Text renderings of a replay summary and a what-if answer (what `autopower replay` prints).
"""

from __future__ import annotations

import math
from typing import Any


def _s(x: float | None, unit: str = "s", digits: int = 1) -> str:
    return "—" if x is None else f"{x:,.{digits}f} {unit}"


def _joules(x: float) -> str:
    # rounded first: a battery metered a fraction of a joule past empty printed as "-0"
    return f"{round(x):,}" if math.isfinite(x) else f"{x}"


def render_text(summary: dict[str, Any]) -> str:
    s = summary
    lines = [f"recording {s['recording']} ({s['kind']}, scenario {s['scenario'] or '?'}, "
             f"policy {s['policy'] or '—'})",
             f"mission time {s['mission']['start_s']:,.1f} s → {s['mission']['end_s']:,.1f} s "
             f"({s['mission']['covered_s']:,.1f} s)", ""]
    lines.append(f"{'robot':<8}{'initial J':>12}{'final J':>12}{'power W':>10}{'lifetime':>16}")
    for r, v in s["robots"].items():
        life = _s(v["lifetime_s"]) + (" " if v["ran_dry_at_s"] is not None else "*")  # the column stays aligned
        lines.append(f"{r:<8}{_joules(v['initial_j']):>12}{_joules(v['final_j']):>12}"
                     f"{(v['power_w'] or 0):>10.3f}{life:>17}")
    fd = s["first_dry"]
    if fd:
        lines.append(f"first to run dry: {fd['robot']} at {fd['at_s']:,.1f} s"
                     + (" (projected at the recorded mean power)" if fd["projected"] else ""))
    lines.append("* projected")
    m = s["migrations"]
    lines += ["", f"decisions: {s['decisions']}; migrations: {m['count']}"
              + (f", downtime total {m['downtime_ms_total']:.1f} ms, worst {m['downtime_ms_max']:.1f} ms"
                 if m["downtime_ms_total"] is not None else "")]
    for mig in m["list"][:20]:
        move = f"{mig['stage']} {mig['from'] or '?'} → {mig['to'] or '?'}: " if mig.get("stage") else ""
        lines.append(f"  {mig['t_s']:>10,.1f} s  {move}{mig['text']}")
    if len(m["list"]) > 20:
        lines.append(f"  ... {len(m['list']) - 20} more")
    wall = s.get("speed") is not None
    lines += ["", f"faults: {len(s['faults'])} (at: mission time; after the injection: "
              + ("wall seconds, what the operator saw, then mission seconds)" if wall else "mission seconds)")]
    for f in s["faults"]:
        def after(key: str) -> str:
            if not wall:
                return _s(f[f"{key}_mission_s"], "s", 3)  # noqa: B023 (called in this iteration)
            return f"{_s(f[f'{key}_wall_s'], 's wall', 3)} ({_s(f[f'{key}_mission_s'], 's mission', 2)})"  # noqa: B023 (called in this iteration)
        by = f" by {f['reconfigured_by']}" if f.get("reconfigured_by") else ""
        lines.append(f"  {f['at_mission_s']:>10,.1f} s  {f['kind']:<10} {f['target']:<14} detected {after('detected')}, "
                     f"reconfigured {after('reconfigured')}{by}  ({f['text']})")
    e = s["energy"]
    over = e.get("overhead_j") or {}
    lines += ["", f"energy: metered {e['metered_j']:,.1f} J, model {_s(e['model_j'], 'J')}, error "
              + ("—" if e["error_pct"] is None else f"{e['error_pct']:+.2f} %")
              + (" (metered minus overheads the model leaves out: "
                 + ", ".join(f"{k} {v:,.2f} J" for k, v in over.items()) + ")" if any(over.values()) else "")]
    per_robot = e.get("per_robot") or {}
    if any(any((v.get("overhead_j") or {}).values()) for v in per_robot.values()):
        # each robot's battery drop split: what the model's steady state prices (idle, component runs,
        # chain packets, sleeping radios) and each overhead it leaves out
        kinds = [k for k in ("control", "runtime", "migration", "recovery", "backlog")
                 if any((v.get("overhead_j") or {}).get(k) for v in per_robot.values())]
        lines.append(f"  {'split':<8}{'chains J':>12}" + "".join(f"{k + ' J':>13}" for k in kinds))
        for r, v in sorted(per_robot.items()):
            over = v.get("overhead_j") or {}
            lines.append(f"  {r + ':':<8}{v['metered_j'] - sum(over.values()):>12,.2f}"
                         + "".join(f"{over.get(k, 0.0):>13,.2f}" for k in kinds))
    control = {r: v["control_bytes"] for r, v in per_robot.items() if v.get("control_bytes")}
    if any(c["sent"] or c["received"] for c in control.values()):
        lines.append("control plane (measured on each robot's links: the bytes beyond its chain packets, of all "
                     "the bytes on them; charged apart as `control`): " + "; ".join(
                         f"{r} sent {c['sent']:,} of {c['link_sent']:,} B, received {c['received']:,} of "
                         f"{c['link_received']:,} B" for r, c in sorted(control.items())))
    cpu = {r: v["cpu_s"] for r, v in per_robot.items() if v.get("cpu_s")}
    if any(c["runtime"] for c in cpu.values()):
        runtime_j = {r: ((per_robot[r].get("overhead_j") or {}).get("runtime") or 0.0) for r in cpu}
        lines.append("runtime CPU (each robot's process beyond its component code, on the computer that ran it; "
                     "charged apart as `runtime` through its platform's slowdown): " + "; ".join(
                         f"{r} {c['runtime']:,.2f} s ({runtime_j[r]:,.2f} J) beside {c['component']:,.2f} s of "
                         "components" for r, c in sorted(cpu.items())))
    o = s["outputs"]
    if o["recorded"]:
        lines.append((f"outputs: {o['produced']} produced, " if o.get("produced") else "outputs: ")
                     + f"{sum(c['outputs'] for c in o['chains'].values())} recorded, "
                     f"{o['lost']} lost, {o['duplicated']} duplicated; {o.get('resent', 0)} frame(s) resent from "
                     f"custody after silent losses" + (f", {o['given_up']} given up" if o.get("given_up") else "")
                     + (f"; {o['held_dropped']} {'more ' if o.get('held_dropped_known') else ''}dropped by "
                        "robots cut off from their sink too long (beyond their hold budget, `[delivery] "
                        "hold_budget_mb`, the oldest results go)" if o.get("held_dropped") else "")
                     + (f"; {o['superseded']} of latest-only chains (`keep = \"latest\"`) replaced in a robot's "
                        "hold by a newer one (delivered, or in hand at the stop)" if o.get("superseded") else "")
                     + (f"; {o['died_with_process']} of a robot's chains died with its crashed process (its memory only)"
                        if o.get("died_with_process") else "")
                     + (f"; {o['unrecorded']} delivered by a sink killed before it flushed their recording "
                        "(named by its journal)" if o.get("unrecorded") else "")
                     + (f"; {o['in_flight']} in flight when the team stopped" if o.get("in_flight") else "")
                     + (f"; {o['abandoned']} abandoned when their chain restarted in a new run"
                        if o.get("abandoned") else ""))
    lines += ["", "invariants:"]
    for inv in s["invariants"]:
        mark = {True: "ok  ", False: "FAIL", None: "n/a "}[inv["ok"]]
        lines.append(f"  [{mark}] {inv['name']}: {inv['detail']}")
    if "what_if" in s:
        lines += ["", render_what_if(s["what_if"])]
    return "\n".join(lines)


def render_what_if(w: dict[str, Any]) -> str:
    lines = [f"what if, from the recorded state at {w['at_s']:,.1f} s "
             f"(settings: {', '.join(f'{k}={v}' for k, v in w['settings'].items() if v)}):"]
    lines.append("  recorded energies: " + ", ".join(f"{r} {e:,.0f} J" for r, e in w["state"]["energies_j"].items())
                 + (f"; unavailable: {', '.join(w['unavailable'])}" if w.get("unavailable") else ""))
    rec, plan_ = w["recorded"], w["plan"]
    stages = sorted(set(rec["allocation"]) | set(plan_["allocation"]))
    lines.append(f"  {'stage':<10}{'run did':<12}{'plan':<12}")
    for st in stages:
        a, b = rec["allocation"].get(st, "—"), plan_["allocation"].get(st, "—")
        lines.append(f"  {st:<10}{a:<12}{b:<12}" + ("" if a == b else "  ← moves"))
    lines.append(f"  lifetime from here: run's allocation {_s(rec['lifetime_s'])}, plan {_s(plan_['lifetime_s'])}"
                 + ("" if w["gain_s"] is None else f" (gain {w['gain_s']:+,.1f} s)"))
    if rec["note"]:
        lines.append(f"  note: {rec['note']}")
    for chain, why in plan_["dropped_chains"].items():
        lines.append(f"  dropped {chain}: {why}")
    if w.get("policy"):
        p = w["policy"]
        lines.append(f"  policy {p['name']}: lifetime {_s(p['lifetime_s'])}, first dry {p['first_dry']}, "
                     f"{p['decisions']} decision(s), {p['migrations']} migration(s) ({p['note']})")
    return "\n".join(lines)
