"""Fault schedules: what goes wrong, when, drawn from a seed (swarm testing) or read from JSON.

Each seed enables a random subset of the fault kinds and draws its faults from that subset only,
so one seed hammers a few mechanisms hard instead of every one lightly. Every fault starts after
the warm-up and ends before the mission does: the quiet phase after it has nothing but healing.
"""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass

from autopower.errors import AutoPowerError
from autopower.model.network import build_network
from autopower.model.scenario import Scenario

# kind -> (shortest, longest) duration in seconds (0: happens at once)
KINDS: dict[str, tuple[float, float]] = {
    "cut": (0.5, 15.0),  # a link, both ways
    "cut-one-way": (0.5, 15.0),  # a -> b only
    "partition": (1.0, 15.0),  # every link between `nodes` and the others
    "loss": (2.0, 20.0),  # a link loses each message with probability p
    "duplicate": (2.0, 20.0),  # a link delivers each message twice with probability p
    "reorder": (2.0, 20.0),  # a link delays each message by up to p seconds more
    "crash": (0.5, 5.0),  # robot a is killed, and restarted from its stores after the duration
    "freeze": (0.2, 5.0),  # node a handles nothing for the duration (its timers run late)
    "basestation-crash": (0.5, 5.0),  # the base station is killed; a new one takes the team over
    "migrate": (0.0, 0.0),  # the operator moves stage a to node b
    "toggle": (1.0, 15.0),  # the operator disables chain a, and enables it after the duration
    # radio links as they are (issue 31): appended, so that a plan drawing from the kinds above
    # draws the same faults as before
    "flap": (4.0, 20.0),  # a link goes down and up again every p seconds (edge of range)
    "roam": (0.05, 2.0),  # a link's short outage: 50-150 ms with 802.11r, seconds without
    "rate": (2.0, 20.0),  # a link carries only the share p of its medium's rate (a robot moving away)
}
LINK_FAULTS = ("cut", "cut-one-way", "loss", "duplicate", "reorder", "flap", "roam", "rate")
WARMUP_S = 10.0  # no fault before the team has started its mission


@dataclass(frozen=True)
class Fault:
    kind: str
    t: float  # when it starts (simulated seconds)
    duration: float = 0.0
    a: str = ""  # a node, stage or chain
    b: str = ""  # a peer node, or where a stage goes
    nodes: tuple[str, ...] = ()  # a partition's side
    p: float = 0.0  # a probability (loss, duplicate), seconds (reorder, flap) or a share of the rate (rate)

    @property
    def end(self) -> float:
        return self.t + self.duration

    def to_json(self) -> dict:
        out = {"kind": self.kind, "t": self.t, "duration": self.duration}
        out.update({k: v for k, v in (("a", self.a), ("b", self.b), ("p", self.p)) if v})
        if self.nodes:
            out["nodes"] = list(self.nodes)
        return out

    @classmethod
    def from_json(cls, obj) -> "Fault":
        if not isinstance(obj, dict) or obj.get("kind") not in KINDS:
            raise AutoPowerError(f"not a fault: {str(obj)[:120]} (kinds: {', '.join(KINDS)})")
        try:
            return cls(kind=obj["kind"], t=float(obj["t"]), duration=float(obj.get("duration", 0.0)),
                       a=str(obj.get("a", "")), b=str(obj.get("b", "")),
                       nodes=tuple(str(n) for n in obj.get("nodes", ())), p=float(obj.get("p", 0.0)))
        except (KeyError, TypeError, ValueError) as exc:
            raise AutoPowerError(f"fault {str(obj)[:120]}: {exc}") from None

    def describe(self) -> str:
        what = {"partition": "{" + ",".join(self.nodes) + "}", "migrate": f"{self.a}->{self.b}",
                "cut-one-way": f"{self.a}->{self.b}"}.get(self.kind, "-".join(x for x in (self.a, self.b) if x))
        extra = f" p={self.p:g}" if self.p else ""
        return f"{' '.join(x for x in (self.kind, what) if x)}{extra} at {self.t:.3f} s for {self.duration:.3f} s"


def check_targets(scenario: Scenario, faults: list[Fault]) -> None:
    """Every fault names nodes, links, stages and chains of ``scenario`` (a replay file may not)."""
    nodes = set(scenario.node_names())
    robots = {r.name for r in scenario.robots}
    links = {frozenset((l.a, l.b)) for l in build_network(scenario).links}
    stages = {s.name for c in scenario.chains for s in c.stages}
    chains = {c.name for c in scenario.chains}
    for f in faults:
        if f.kind in LINK_FAULTS:
            ok = frozenset((f.a, f.b)) in links and (f.kind not in ("flap", "rate") or f.p > 0)
        elif f.kind == "partition":
            ok = bool(f.nodes) and set(f.nodes) < nodes
        elif f.kind == "crash":
            ok = f.a in robots
        elif f.kind == "freeze":
            ok = f.a in nodes
        elif f.kind == "migrate":
            ok = f.a in stages and f.b in nodes
        elif f.kind == "toggle":
            ok = f.a in chains
        else:
            ok = True
        if not ok or f.t < 0 or f.duration < 0:
            raise AutoPowerError(f"fault '{f.describe()}' does not fit scenario {scenario.name}")


def draw(scenario: Scenario, seed: int, n_faults: int, mission_s: float,
         kinds: tuple[str, ...] = tuple(KINDS)) -> tuple[tuple[str, ...], list[Fault]]:
    """The kinds a seed enables (a random subset of ``kinds``) and its ``n_faults`` faults within
    ``[WARMUP_S, mission_s)``."""
    rng = random.Random(f"autopower-sim-faults-{seed}")
    kinds = [k for k in KINDS if k in kinds]
    enabled = tuple(k for k in kinds if k in set(rng.sample(kinds, rng.randint(1, len(kinds)))))
    nodes = list(scenario.node_names())
    robots = [r.name for r in scenario.robots]
    links = sorted(tuple(sorted((l.a, l.b))) for l in build_network(scenario).links)
    stages = [s.name for c in scenario.chains for s in c.stages]
    chains = [c.name for c in scenario.chains]
    faults = []
    if mission_s <= WARMUP_S:
        return enabled, faults
    for _ in range(n_faults):
        kind = rng.choice(enabled)
        t = round(rng.uniform(WARMUP_S, mission_s), 3)
        low, high = KINDS[kind]
        duration = round(min(rng.uniform(low, high), mission_s - t), 3)
        a, b = rng.choice(links) if kind in LINK_FAULTS else ("", "")
        if kind == "cut-one-way" and rng.random() < 0.5:
            a, b = b, a
        fault = Fault(kind=kind, t=t, duration=duration, a=a, b=b)
        if kind == "partition":
            side = tuple(sorted(rng.sample(nodes, rng.randint(1, len(nodes) - 1))))
            fault = dataclasses.replace(fault, nodes=side)
        elif kind in ("loss", "duplicate"):
            fault = dataclasses.replace(fault, p=round(rng.uniform(0.05, 0.5), 3))
        elif kind == "reorder":
            fault = dataclasses.replace(fault, p=round(rng.uniform(0.005, 0.2), 4))
        elif kind == "flap":
            fault = dataclasses.replace(fault, p=round(rng.uniform(0.3, 3.0), 3))
        elif kind == "rate":
            fault = dataclasses.replace(fault, p=round(rng.uniform(0.05, 0.5), 3))
        elif kind == "crash":
            fault = dataclasses.replace(fault, a=rng.choice(robots))
        elif kind == "freeze":
            fault = dataclasses.replace(fault, a=rng.choice(nodes))
        elif kind == "migrate":
            fault = dataclasses.replace(fault, a=rng.choice(stages), b=rng.choice(nodes))
        elif kind == "toggle":
            fault = dataclasses.replace(fault, a=rng.choice(chains))
        faults.append(fault)
    faults.sort(key=lambda f: (f.t, f.kind))
    return enabled, faults
