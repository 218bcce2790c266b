"""Why each stage runs where it runs: the plan against its most natural alternative.

For a stage placed away from its source robot the alternative is running it locally; for a
local stage it is the best other host. Loads are additive, so an alternative costs one vector
difference, not a full re-evaluation (this stays cheap at 300 stages).
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from autopower.model.energy import Evaluation, LoadSpace, dag_load, load_of
from autopower.model.network import Network
from autopower.planner.problem import Problem


def _fmt_life(life: float) -> str:
    return "infeasible" if not np.isfinite(life) else f"{life:,.1f} s"


def explain(problem: Problem, network: Network, allocation: dict[str, str], evaluation: Evaluation,
            stages: Collection[str] | None = None) -> dict[str, str]:
    """Why each stage runs where it runs (only ``stages``, when given), and why each unroutable
    chain is not placed."""
    space = LoadSpace(problem.scenario, network, problem.accounting, problem.energies_j)
    base = load_of(space, problem.chains, allocation)
    base_power = space.total_power(base[None, :])[0]
    base_life = space.lifetimes(base[None, :])[0]
    parts = space.breakdown(base[None, :])
    reasons: dict[str, str] = {}
    bottleneck = evaluation.bottleneck
    head = f"{bottleneck} is the bottleneck" if bottleneck else "no robot limits the team"
    for chain in problem.chains:
        hosts = tuple(allocation[s.name] for s in chain.stages)
        old = space.chain_load(chain, hosts)
        for k, stage in enumerate(chain.stages):
            if stages is not None and stage.name not in stages:
                continue
            host = hosts[k]
            alternatives = [h for h in problem.hosts[stage.name] if h != host]
            if not alternatives:
                reasons[stage.name] = f"{stage.name} → {host}: the only allowed host"
                continue

            flows = [f for f in problem.flows if stage.name in (f.producer, f.consumer)]  # DAG edges it moves

            def trial(alt: str) -> np.ndarray:
                new_hosts = hosts[:k] + (alt,) + hosts[k + 1:]  # noqa: B023 (called in this iteration)
                moved = dag_load(space, problem.chains, {**allocation, stage.name: alt}, flows) if flows else 0.0  # noqa: B023 (called in this iteration)
                kept = dag_load(space, problem.chains, allocation, flows) if flows else 0.0  # noqa: B023 (called in this iteration)
                return base - old + space.chain_load(chain, new_hosts) + moved - kept  # noqa: B023 (called in this iteration)

            if host != chain.source and chain.source in alternatives:
                alt = chain.source
            else:
                lives = space.lifetimes(np.stack([trial(h) for h in alternatives]))  # one batch
                alt = alternatives[int(np.argmax(lives))]  # (the first of equals, as max() over them)
            load = trial(alt)
            alt_life = space.lifetimes(load[None, :])[0]
            alt_power = space.total_power(load[None, :])[0]
            where = "locally" if alt == chain.source else f"on {alt}"
            text = f"{stage.name} → {host}{' (local)' if host == chain.source else ''}: {head}."
            if not np.isfinite(alt_life):
                violated = _violations(space, load)
                text += f" Running it {where} is infeasible ({violated})."
                text += _flows_text(space, {**allocation, stage.name: alt}, flows, f"{where}, ", load)
            else:
                delta = alt_life / base_life - 1 if np.isfinite(base_life) and base_life > 0 else 0.0
                text += f" Running it {where} gives {_fmt_life(alt_life)} ({delta:+.1%})"
                # The robots whose draw changes most explain the trade-off.
                alt_cpu = space.breakdown(load[None, :])["cpu_w"][0]
                saved = alt_power - base_power  # > 0: this placement draws less than the alternative
                changes = []
                for i in np.argsort(-np.abs(saved))[:2]:
                    if abs(saved[i]) < 1e-7:
                        continue
                    cpu_saved = float(alt_cpu[i] - parts["cpu_w"][0, i])
                    radio_saved = float(saved[i]) - cpu_saved
                    verb = "saves" if saved[i] > 0 else "costs"
                    changes.append(f"this placement {verb} {abs(saved[i]):.4f} W on {space.robots[i]} "
                                   f"({_signed('CPU', cpu_saved)}, {_signed('radio', radio_saved)})")
                text += ("; " + "; ".join(changes)) if changes else ""
                text += "."
                text += _flows_text(space, {**allocation, stage.name: alt}, flows, f"{where}, ", load)
            text += _flows_text(space, allocation, flows, "here, ", base)
            reasons[stage.name] = text
    for name, why in problem.unroutable.items():
        reasons[name] = f"not placed: {why}"
    return reasons


def _violations(space: LoadSpace, load: np.ndarray) -> str:
    cpu, send, recv = (x[0] for x in space.split(load[None, :]))
    out = []
    for node, i in space.node_index.items():
        if cpu[i] > 1:
            out.append(f"{node} CPU at {cpu[i]:.0%}")
        if i in space.radio_limited_rows:
            for medium, j in space.medium_index.items():
                busy = send[i, j] + recv[i, j]
                if busy > 1:
                    out.append(f"{node} {medium} radio at {busy:.0%}")
    return ", ".join(out) or "limits exceeded"


def _signed(part: str, saved_w: float) -> str:
    return f"{'saves' if saved_w >= 0 else 'costs'} {abs(saved_w):.4f} W {part}"


def _flows_text(space: LoadSpace, allocation: dict[str, str], flows, where: str, load: np.ndarray) -> str:
    """The DAG flows a stage's placement routes, each named, with its path and medium; a flow
    crossing an over-limit radio is marked as the offending one."""
    if not flows:
        return ""
    _, send, recv = (x[0] for x in space.split(load[None, :]))
    parts = []
    for flow in flows:
        src, dst = allocation[flow.producer], allocation[flow.consumer]
        if src == dst:
            parts.append(f"flow {flow.name} stays on {src}")
            continue
        hops = space.network.route(src, dst) if space.network.reachable(src, dst) else []
        over = [f"{u} {m}" for u, v, m in hops for n in (u, v)
                if space.node_index[n] in space.radio_limited_rows
                and send[space.node_index[n], space.medium_index[m]] + recv[space.node_index[n], space.medium_index[m]] > 1]
        path = " → ".join([src, *(f"{v} ({m})" for _, v, m in hops)]) if hops else f"{src} ↛ {dst} (no route)"
        parts.append(f"flow {flow.name} ({flow.n_bytes} B) {path}" + (" crosses an over-limit radio" if over else ""))
    sentence = where + "; ".join(parts)
    return f" {sentence[:1].upper()}{sentence[1:]}."
