"""Random but honest scenarios: the paper's platforms and radios, teams of any size.

Used by the property tests (MILP == exhaustive), the planner benchmark and the simulator's
random-scenario sweeps. Everything is a function of the seed.
"""

from __future__ import annotations

import numpy as np

from autopower.model.loading import load_scenario
from autopower.model.scenario import (
    LAPTOP_ROBOT,
    ROBOT_ROBOT,
    Chain,
    ComponentSpec,
    LinkSpec,
    NetworkSpec,
    Platform,
    Radio,
    Robot,
    Scenario,
    Stage,
)


def random_scenario(
    seed: int,
    robots: int = 3,
    chains: int = 5,
    *,
    topology: str = "fully-connected",
    accounting: str = "paper",
    multi_stage: bool = False,
    energy_spread: float = 0.5,
) -> Scenario:
    """A team of `robots` Sitsang robots and `chains` localisation/blob-like chains.

    Latencies, periods, message sizes and energies are drawn around the paper's values so that
    both local and offloaded placements are sometimes feasible and sometimes not.
    """
    rng = np.random.default_rng(seed)
    paper = load_scenario("paper-fig7")
    names = [f"r{i + 1}" for i in range(robots)]
    team = tuple(
        Robot(name=n, platform="sitsang", energy_j=float(round(64000 * (1 - energy_spread * rng.random()))),
              sensors=frozenset({"laser", "odometry", "camera"}))
        for n in names
    )
    components = {}
    out_chains = []
    for k in range(chains):
        kind = rng.choice(["loc", "blob"])
        comp = f"C{k}"
        if kind == "loc":
            period = float(rng.choice([1.0, 2.0, 4.0]))
            sitsang = float(rng.uniform(0.1, 0.9)) * period / 2
            sizes = [int(rng.integers(500, 2000)), int(rng.integers(300, 1200))]
        else:
            period = float(rng.choice([0.25, 0.5, 1.0]))
            sitsang = float(rng.uniform(0.05, 0.5)) * period
            sizes = [int(rng.choice([2000, 20000, 230415])), int(rng.integers(50, 400))]
        components[comp] = ComponentSpec(name=comp, latency_s={"sitsang": sitsang, "laptop": sitsang / rng.uniform(10, 250)})
        source = names[int(rng.integers(robots))]
        sink = source if kind == "loc" else "laptop"
        if multi_stage and rng.random() < 0.4:
            comp2 = f"C{k}b"
            components[comp2] = ComponentSpec(name=comp2, latency_s={"sitsang": sitsang / 2, "laptop": sitsang / 40})
            stages = (Stage(name=f"{comp}-s0", component=comp), Stage(name=f"{comp}-s1", component=comp2))
            sizes = [sizes[0], int(rng.integers(100, 3000)), sizes[1]]
        else:
            stages = (Stage(name=f"{comp}-{source}", component=comp),)
        out_chains.append(Chain(name=f"{comp}-{source}", source=source, sink=sink, period_s=period,
                                stages=stages, message_bytes=tuple(sizes)))
    return _synthetic(paper, f"random-{seed}-{robots}x{chains}", "synthetic", f"<random seed {seed}>", accounting,
                      team, topology, components, out_chains)


def _synthetic(paper: Scenario, name: str, description: str, source_path: str, accounting: str, team, topology: str,
               components, chains) -> Scenario:
    """A synthetic team on the paper's platforms and radios, the laptop as base station, media to
    choose between 802.11a and GSM (laptop-robot) or Bluetooth (robot-robot)."""
    network = NetworkSpec(topology=topology, relay=team[0].name,
                          laptop_robot_media=("802.11a", "gsm"), robot_robot_media=("802.11a", "bluetooth"),
                          analyze_topologies=(topology,))
    return Scenario(
        name=name,
        description=description,
        source_path=source_path,
        accounting=accounting,
        lifetime_rounding_s=0.8,
        platforms=dict(paper.platforms),
        radios=dict(paper.radios),
        robots=tuple(team),
        basestation="laptop",
        basestation_platform="laptop",
        network_spec=network,
        components=components,
        chains=tuple(chains),
    )


def fleet_scenario(robots: int, components: int, seed: int = 0, accounting: str = "paper") -> Scenario:
    """A large team for scaling: `components` single-stage chains spread over the robots."""
    return random_scenario(seed, robots, components, accounting=accounting)


def loaded_fleet_scenario(robots: int, seed: int = 0, *, hosts: str = "any", accounting: str = "paper") -> Scenario:
    """A fleet where every robot is loaded: each runs three chains of its own, a localisation
    (sink: itself), a blob finder (sink: the base station) and a mapper (sink: the base station),
    with latencies, periods and sizes drawn around the paper's per robot.

    hosts="any": any node may run any stage; hosts="own": a robot's stages run on that robot or
    the base station (the laptop), the deployment the paper's robots would use at scale.
    """
    if hosts not in ("any", "own"):
        raise ValueError(f"hosts must be 'any' or 'own', not {hosts!r}")
    rng = np.random.default_rng([seed, robots, 0xF1EE7])
    paper = load_scenario("paper-fig7")
    names = [f"r{i + 1}" for i in range(robots)]
    team = tuple(Robot(name=n, platform="sitsang", energy_j=float(round(64000 * (1 - 0.5 * rng.random()))),
                       sensors=frozenset({"laser", "odometry", "camera"}))
                 for n in names)
    components: dict[str, ComponentSpec] = {}
    chains = []
    for robot in names:
        allowed = None if hosts == "any" else (robot, "laptop")
        # (kind, period, share of the period on a Sitsang, sizes in/out, sink)
        loc_period = float(rng.choice([1.0, 2.0, 4.0]))
        blob_period = float(rng.choice([0.5, 1.0]))
        specs = [
            ("Loc", loc_period, float(rng.uniform(0.05, 0.3)), (int(rng.integers(500, 2000)), int(rng.integers(300, 1200))), robot),
            ("Blob", blob_period, float(rng.uniform(0.05, 0.3)), (int(rng.choice([2000, 20000])), int(rng.integers(50, 400))), "laptop"),
            ("Map", 2.0, float(rng.uniform(0.05, 0.3)), (int(rng.integers(2000, 8000)), int(rng.integers(200, 1000))), "laptop"),
        ]
        for kind, period, share, sizes, sink in specs:
            name = f"{kind}-{robot}"
            sitsang = share * period
            components[name] = ComponentSpec(name=name, latency_s={"sitsang": sitsang, "laptop": sitsang / rng.uniform(10, 250)})
            chains.append(Chain(name=name, source=robot, sink=sink, period_s=period,
                                stages=(Stage(name=name, component=name, hosts=allowed),), message_bytes=sizes))
    return _synthetic(paper, f"loaded-fleet-{seed}-{robots}-{hosts}", "synthetic: every robot loaded",
                      f"<loaded fleet seed {seed}>", accounting, team, "fully-connected", components, chains)


def random_dag_scenario(seed: int, robots: int = 3, chains: int = 3, **kwargs) -> Scenario:
    """`random_scenario` made an application DAG (autopower.model.dag): a source-less fan-in
    chain joining 1-3 random stages (sink: the base station or a robot), and sometimes one more
    flow from one chain's stage into a later chain's stage (fan-out + fan-in mid-chain). Flows
    only go from earlier to later chains, so the graph is acyclic."""
    import dataclasses

    from autopower.model.dag import Flow

    base = random_scenario(seed, robots, chains, **kwargs)
    rng = np.random.default_rng([seed, 0xDA6])
    chain_list = list(base.chains)
    stages = [(i, s.name) for i, c in enumerate(chain_list) for s in c.stages]
    picked = rng.choice(len(stages), size=min(len(stages), int(rng.integers(1, 4))), replace=False)
    producers = [stages[int(k)][1] for k in picked]
    period = chain_list[stages[int(picked[0])][0]].period_s
    join = "J"
    components = dict(base.components)
    sitsang = float(rng.uniform(0.02, 0.4)) * period
    components[join] = ComponentSpec(name=join, latency_s={"sitsang": sitsang, "laptop": sitsang / 20})
    sink = str(rng.choice([base.basestation, *(r.name for r in base.robots)]))
    flows = tuple(Flow(producer=p, consumer=join, n_bytes=int(rng.integers(200, 20000))) for p in producers)
    chain_list.append(Chain(name=join, source=sink, sink=sink, period_s=period,
                            stages=(Stage(name=join, component=join),), message_bytes=(0, int(rng.integers(100, 3000))),
                            inputs=flows, sourced=False))
    if len(base.chains) > 1 and rng.random() < 0.5:
        a, b = sorted(int(k) for k in rng.choice(len(base.chains), size=2, replace=False))
        producer = chain_list[a].stages[-1].name
        consumer = chain_list[b]
        extra = Flow(producer=producer, consumer=consumer.stages[-1].name, n_bytes=int(rng.integers(100, 5000)))
        chain_list[b] = dataclasses.replace(consumer, inputs=(*consumer.inputs, extra))
    return dataclasses.replace(base, name=base.name + "-dag", components=components, chains=tuple(chain_list))


__all__ = ["random_scenario", "loaded_fleet_scenario", "random_dag_scenario", "fleet_scenario", "LAPTOP_ROBOT", "ROBOT_ROBOT", "LinkSpec", "Platform", "Radio"]
