"""The live status table `up` and `status` draw (rich)."""

from __future__ import annotations

import time


def render(snap: dict, speed: float):
    """The live status table of `autopower up`."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    from autopower.launch.summary import chain_latencies, keep_up_warning, supervisor_line
    from autopower.model.network import describe_media
    from autopower.model.parts import CPU_RUNTIME

    revisit = snap.get("revisit_at_s")
    parts = [f"{snap.get('scenario')}", f"{snap.get('accounting')} accounting",
             f"t = {snap.get('t_virtual', 0):.0f} s virtual (x{speed:g})", f"policy {snap.get('policy')}",
             f"planned lifetime {snap.get('planned_lifetime_s')} s", f"media {describe_media(snap.get('media'))}"]
    if revisit is not None:  # a time-sharing schedule switches configuration then
        parts.append(f"next phase at t = {revisit:.0f} s")
    if not snap.get("ready"):
        parts.append("placing…")
    head = Text(" · ".join(parts), style="bold")
    warning = keep_up_warning(snap, speed)
    if warning:
        head.append(f"\nwarning: {warning}", style="bold red")
    if snap.get("recording_error"):
        head.append(f"\nRECORDING FAILED: {snap['recording_error']} (stopping the team)", style="bold red")
    # control: the power its links' bytes beyond the chain packets draw (statuses, keep-alives,
    # plans, framing; measured, apart from the plan), and those bytes sent/received so far; runtime:
    # the power its process's own CPU draws (all but component code, through the platform's slowdown),
    # and that CPU in seconds on this computer so far
    robots = Table("robot", "battery", "power W (plan)", "control W (kB out/in)", "runtime W (CPU s)", "CPU", "hosts",
                   "sources (frames/missed)", "links", title="robots", title_justify="left")
    for name, info in snap.get("robots", {}).items():
        st = info.get("status")
        if not st:
            robots.add_row(name, "joining" if info.get("present") else "absent", "", "", "", "", "", "", "")
            continue
        battery = st["battery_j"]
        pct = battery / st["initial_j"] * 100 if st["initial_j"] else 0
        power = sum(st["power_w"].values())
        plan_w = info.get("predicted_w")
        sources = ", ".join(f"{c} {s['produced_total']}/{s['missed']}" for c, s in st["sources"].items())
        links = " ".join(f"{p}{'✓' if up else '✗'}" for p, up in st["links"].items())
        control_w = sum(w for part, w in st["power_w"].items() if part.endswith(":control"))
        out_b, in_b = st.get("control_bytes") or (0, 0)
        runtime_w = st["power_w"].get(CPU_RUNTIME, 0.0)
        robots.add_row(name, f"{battery:,.0f} J ({pct:.1f}%)" + (" DEPLETED" if st["depleted"] else ""),
                       f"{power:.3f} ({plan_w:.3f})" if plan_w else f"{power:.3f}",
                       f"{control_w:.4f} ({out_b / 1e3:,.0f}/{in_b / 1e3:,.0f})",
                       f"{runtime_w:.3f} ({st.get('runtime_cpu_s', 0.0):.1f})",
                       f"{st['cpu_utilisation']:.0%}", ", ".join(st["hosted"]) or "-", sources or "-", links)
    stages = Table("stage", "runs on", "planned", "why", title="components", title_justify="left")
    for stage, want in snap.get("target", {}).items():
        have = snap.get("placement", {}).get(stage, "-")
        moving = snap.get("migrating", {}).get(stage)
        stages.add_row(stage, have + (f" → {moving['to']}" if moving else ""), want,
                       (snap.get("reasons") or {}).get(stage, ""))
    # end to end: from the source's capture to the sink's receipt (wall ms; shaped radios add to it)
    chains = Table("chain", "sink", "outputs", "latency p50", "latency max", "missing", "duplicated",
                   title="chains (end-to-end latency, source to sink)", title_justify="left")
    for chain, c in chain_latencies(snap).items():
        chains.add_row(chain, c["sink"], str(c["outputs"]), _ms(c["p50_ms"]), _ms(c["max_ms"]),
                       str(c["missing"]), str(c["duplicated"]))
    if not chains.row_count:
        chains.add_row("-", "nothing yet", "", "", "", "", "")
    foot = Text("\n".join((snap.get("events") or [])[-4:]), style="dim")
    supervision = snap.get("supervision") or {}
    if supervision.get("events"):  # crashes and restarts by `up`'s supervisor (not the base station's view)
        lines = [supervisor_line(supervision)] + [
            f"{time.strftime('%H:%M:%S', time.localtime(e['t_unix']))} {e['node']} {e['kind']}: {e['detail']}"
            for e in supervision["events"][-3:]]
        foot.append("\n" + "\n".join(lines), style="bold red" if supervision.get("given_up") else "yellow")
    failed = snap.get("failed_stages") or {}
    if failed:  # components stopped for misbehaving, and why (their chains are stopped)
        warn = Text("\n".join(f"FAILED {stage} on {why}" for stage, why in failed.items()), style="bold red")
        return Group(head, robots, stages, chains, warn, foot)
    return Group(head, robots, stages, chains, foot)


def _ms(value) -> str:
    return "-" if value is None else f"{value:,.0f} ms" if value >= 100 else f"{value:.1f} ms"
