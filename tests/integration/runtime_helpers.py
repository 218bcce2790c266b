"""Shared helpers for the runtime's integration tests: real processes, real Zenoh on 127.0.0.1."""

from __future__ import annotations

import time

from autopower.chains import make_component, make_source
from autopower.errors import AutoPowerError
from autopower.launch.summary import overhead_j
from autopower.model.scenario import Scenario
from autopower.node.sequencing import fold_digest
from autopower.node.stages import chain_seed
from autopower.protocol import NodeStatus, StatusDelta, decode
from autopower.protocol.statuses import StatusAssembler


def whole_statuses(payloads) -> list[NodeStatus | None]:
    """Status payloads as one node published them (each whole, or as its change from the last whole
    one: `protocol.statuses`) made whole, in order; None for a change whose whole status is not
    among them."""
    assembler = StatusAssembler()
    return [assembler.whole(decode(p, (NodeStatus, StatusDelta))) for p in payloads]


def sinks_of(snap: dict) -> dict[str, dict]:
    """Every chain's sink statistics, wherever its sink is (a robot or the base station)."""
    out = dict((snap.get("basestation") or {}).get("sinks") or {})
    for info in snap["robots"].values():
        if info.get("status"):
            out.update(info["status"]["sinks"])
    return out


def sources_of(snap: dict) -> dict[str, dict]:
    out = {}
    for info in snap["robots"].values():
        if info.get("status"):
            out.update(info["status"]["sources"])
    return out


def errors_of(snap: dict) -> dict[str, dict]:
    out = {"basestation": (snap.get("basestation") or {}).get("errors", {})}
    for name, info in snap["robots"].items():
        if info.get("status"):
            out[name] = info["status"]["errors"]
    return out


def wait_for(team, predicate, timeout_s: float, what: str) -> dict:
    """Poll snapshots until ``predicate(snapshot)`` holds (bounded; no blind sleeping)."""
    deadline = time.monotonic() + timeout_s
    snap = {}
    while time.monotonic() < deadline:
        team.check_children()
        try:
            snap = team.snapshot()
        except AutoPowerError:
            continue
        if predicate(snap):
            return snap
        time.sleep(0.1)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}; last snapshot: "
                         f"placement={snap.get('placement')} migrating={snap.get('migrating')} "
                         f"sinks={ {c: (s['contiguous'], s['received']) for c, s in sinks_of(snap).items()} if snap else None}")


def settled(snap: dict) -> bool:
    """Ready, and every robot's last status reflects the current plan."""
    return bool(snap.get("ready")) and all(
        info["status"] and info["status"]["plan_epoch"] == snap["epoch"] for info in snap["robots"].values()
        if info["present"])


def reference_digest(scenario: Scenario, chain_name: str, n: int) -> int:
    """Re-run a chain offline for seqs 0..n-1 and fold its outputs like a sink does."""
    chain = scenario.chain(chain_name)
    seed = chain_seed(scenario, chain)
    source = make_source(chain.stages[0].component, chain.source, seed)
    components = [make_component(s.component, chain.source, seed) for s in chain.stages]
    digest = 0
    for seq in range(n):
        data = source.produce(seq)
        for component in components:
            data = component.run(data)
        digest = fold_digest(digest, seq, data)
    return digest


def measured_power(s1: dict, s2: dict, robot: str) -> float:
    """A robot's metered power between two snapshots, less what the model leaves out (migrations,
    recovery, the control plane, the runtime's own CPU: `model.parts.overhead_kind`), as the run
    summary and the replay compare it with the model."""
    a, b = s1["robots"][robot]["status"], s2["robots"][robot]["status"]
    consumed = (a["battery_j"] - b["battery_j"]) - (overhead_j(b) - overhead_j(a))
    return consumed / (b["t_virtual"] - a["t_virtual"])
