"""What the recording says the team was at a moment, and what-if replanning from there.

`recorded_state` reads placement, media, batteries and links at a mission time; `what_if` asks the
planner or a policy what it would have done then, under other options.
"""

from __future__ import annotations

from typing import Any, Mapping

from autopower.errors import AutoPowerError, RecordingError
from autopower.recording.replay import _EPS, _events, _robots
from autopower.recording.telemetry import ALLOCATION, FAULTS, NETWORK, Recording

# ---------------------------------------------------------------------------------------------
# what if
# ---------------------------------------------------------------------------------------------


def _at(times: list[float], values: list, t: float):
    best = None
    for ti, v in zip(times, values, strict=False):
        if ti <= t + _EPS:
            best = v
        else:
            break
    return best


def recorded_state(rec: Recording, at_s: float | None = None) -> dict[str, Any]:
    """Energies, allocation and links in force at `at_s` (default: the end of the recording)."""
    robots = _robots(rec)
    if at_s is None:
        at_s = max((rec.series(f"robots/{r}/battery_j")[0][-1] for r in robots), default=0.0)
    energies = {}
    for r in robots:
        ts, bs = rec.series(f"robots/{r}/battery_j")
        b = _at(ts, bs, at_s)
        energies[r] = bs[0] if b is None else b
    allocation: dict[str, str] = {}
    rows = sorted(rec.graphs.get(ALLOCATION, []), key=lambda row: row[0])
    chosen = None
    for row in rows:
        if row[0] <= at_s + _EPS:
            chosen = row
    if chosen is not None:
        allocation = {e["first"]: e["second"] for e in (chosen[2] or [])}
    links = None
    rows = sorted(rec.graphs.get(NETWORK, []), key=lambda row: row[0])
    chosen = None
    for row in rows:
        if row[0] <= at_s + _EPS:
            chosen = row
    if chosen is not None:
        links = []
        for e in chosen[2] or []:
            a, b = e["first"], e["second"]
            lo, hi = sorted((a, b))
            med = [(t, text) for t, text, _ in rec.log(f"team/links/{lo}-{hi}/medium") if t <= at_s + _EPS]
            medium = med[-1][1] if med else None
            links.append((a, b, medium))
    return {"at_s": at_s, "energies_j": energies, "allocation": allocation, "links": links}


def what_if(rec: Recording, *, at_s: float | None = None, accounting: str | None = None,
            energies: Mapping[str, float] | None = None, policy: str | None = None, topology: str | None = None,
            disable: tuple[str, ...] = (), scenario=None, control_plane: bool | None = None) -> dict[str, Any]:
    """Replan offline from the recorded state at `at_s` with other settings; compare with the run.

    Robots with no battery data, an empty battery, or whose liveliness was lost (and not back)
    by then are unavailable. Returns ``{"at_s", "unavailable", "settings", "state": {"energies_j", "allocation", "links"},
    "recorded": {"allocation", "lifetime_s", "note"}, "plan": {"allocation", "media", "lifetime_s",
    "bottleneck", "reasons", "method", "dropped_chains"}, "gain_s", "policy": {...} | null}``.
    ``control_plane``: charge the team's statuses and keep-alives (`model.control_plane`) or not;
    None: as the scenario says.
    """
    from autopower.model.loading import load_scenario
    from autopower.model.network import Link, Network
    from autopower.planner import PlanRequest, evaluate_in, make_problem, plan

    if scenario is None:
        name = rec.properties.get("scenario")
        if not name:
            raise RecordingError("the recording does not name its scenario; pass --scenario to --what-if")
        scenario = load_scenario(name)
    scenario = scenario.with_control_plane(control_plane)
    state = recorded_state(rec, at_s)
    energies_j = {**state["energies_j"], **dict(energies or {})}
    unknown = set(energies or {}) - {r.name for r in scenario.robots}
    if unknown:
        raise AutoPowerError(f"--energy names unknown robot(s) {', '.join(sorted(unknown))}; robots: "
                             f"{', '.join(r.name for r in scenario.robots)}")
    bad = set(disable) - {c.name for c in scenario.chains}
    if bad:
        raise AutoPowerError(f"--disable names unknown chain(s) {', '.join(sorted(bad))}; chains: "
                             f"{', '.join(c.name for c in scenario.chains)}")
    # robots the run did not have then: never recorded, empty, or lost (and not back) at that time
    lost: set[str] = set()
    for t, _text, p in _events(rec, FAULTS):
        if p is not None and p.get("type") == "fault" and p.get("kind") == "node-lost" and t <= state["at_s"] + _EPS:
            (lost.add if p.get("phase") == "detected" else lost.discard)(p.get("target"))
    robots = {r.name for r in scenario.robots}
    gone = {r for r in robots if r not in energies_j or energies_j[r] <= _EPS} | (lost & robots)
    if gone >= robots:  # at the very end everyone may be gone: plan for those with energy left
        gone = {r for r in robots if r not in energies_j or energies_j[r] <= _EPS}
    dry = frozenset(gone)
    alive = {r: max(e, 1e-9) for r, e in energies_j.items()}
    recorded_alloc = state["allocation"]
    # chains the run was not running then (operator-disabled, or dropped) stay off, plus --disable
    stages_run = set(recorded_alloc)
    off = {c.name for c in scenario.chains if recorded_alloc and not all(s.name in stages_run for s in c.stages)}
    off |= set(disable)
    network = None
    if topology is None and state["links"] is not None and all(m for *_, m in state["links"]):
        bs = scenario.basestation
        links = [Link(a=a, b=b, medium=m, group="laptop-robot" if bs in (a, b) else "robot-robot")
                 for a, b, m in state["links"]]
        try:
            network = Network(scenario.node_names(), bs, links, topology=rec.properties.get("topology") or "explicit")
        except AutoPowerError:
            network = None
    request = PlanRequest(scenario=scenario, network=network, topology=topology or rec.properties.get("topology"),
                          energies_j=alive, disabled_chains=frozenset(off), unavailable_nodes=dry,
                          accounting=accounting or rec.properties.get("accounting"))
    best = plan(request)
    recorded_life, note = None, ""
    if recorded_alloc:
        try:
            problem = make_problem(request)
            placed = {s.name for c in problem.chains for s in c.stages}
            ev = evaluate_in(problem, best.network if network is None else network,
                             {s: h for s, h in recorded_alloc.items() if s in placed})
            recorded_life = ev.lifetime_s
            if not ev.feasible:
                note = "the recorded allocation is infeasible under these settings: " + "; ".join(
                    v.message for v in ev.violations)
        except AutoPowerError as exc:
            note = f"the recorded allocation cannot run under these settings: {exc}"
    out = {
        "at_s": state["at_s"],
        "unavailable": sorted(dry),
        "settings": {"accounting": request.accounting or scenario.accounting, "topology": topology,
                     "energies_j": dict(energies or {}), "disable": sorted(disable), "policy": policy,
                     "control_plane": scenario.control_plane.enabled},
        "state": {"energies_j": state["energies_j"], "allocation": recorded_alloc,
                  "links": [list(l) for l in state["links"]] if state["links"] is not None else None},
        "recorded": {"allocation": recorded_alloc, "lifetime_s": recorded_life, "note": note},
        "plan": {"allocation": dict(best.allocation), "media": best.network.media_by_group(),
                 "lifetime_s": best.lifetime_s, "bottleneck": best.evaluation.bottleneck,
                 "reasons": dict(best.reasons), "method": best.method, "dropped_chains": dict(best.dropped)},
        "gain_s": (best.lifetime_s - recorded_life) if (best.lifetime_s and recorded_life) else None,
        "policy": None,
    }
    if policy is not None:
        from autopower.model.mission_events import EventScript
        from autopower.simulation.simulator import simulate

        sc = scenario.with_energies({r: e for r, e in alive.items()}).with_accounting(request.accounting)
        script = EventScript(source_path="<replay what-if>", initially_absent=frozenset(dry))
        result = simulate(sc, script, policy=policy, topology=topology or rec.properties.get("topology"))
        out["policy"] = {"name": policy, "lifetime_s": result.lifetime_s, "first_dry": result.first_dry,
                         "end_reason": result.end_reason, "decisions": len(result.decisions),
                         "migrations": len(result.migrations),
                         "note": "simulated from the recorded energies with no further events"}
    return out


# ---------------------------------------------------------------------------------------------
# text rendering
# ---------------------------------------------------------------------------------------------


