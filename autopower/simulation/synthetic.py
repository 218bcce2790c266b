"""Scenarios of any size on the paper's platforms and radios: random ones and the paper's fleet.

`random_scenario`, `fleet_scenario`, `loaded_fleet_scenario` and `random_dag_scenario` draw
latencies, periods and sizes around the paper's: they serve the property tests (MILP ==
exhaustive), the planner benchmark and the simulator's random-scenario sweeps. `paper_fleet` is
the paper's own mission on N robots, written as a scenario file: what `autopower scenarios fleet`
writes and bench/bench_loading.py checks. Everything is a function of the seed.
"""

from __future__ import annotations

import json
import math
import re
from importlib import resources
from typing import Any, Sequence

import numpy as np

from autopower.errors import ScenarioError
from autopower.model.loading import load_scenario, load_toml, parse_scenario
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


PAPER_FLEET_TOPOLOGIES = ("fully-connected", "relay", "neighbours")


def ring_links(robots: int, neighbours: int) -> list[tuple[int, int]]:
    """The robot-robot links of robots 1..N standing in a ring, each in radio range of its
    ``neighbours`` nearest robots on either side: (i, j) with i < j, each pair once. A ring of
    2 x neighbours + 1 robots or fewer is fully connected."""
    pairs = {tuple(sorted((i, (i + d - 1) % robots + 1))) for i in range(1, robots + 1)
             for d in range(1, neighbours + 1)}
    return sorted(p for p in pairs if p[0] != p[1])


def paper_fleet(robots: int, cameras: int | None = None, *, topology: str = "fully-connected",
                media: Sequence[str] = (), seed: int = 0, neighbours: int = 1) -> tuple[str, Scenario]:
    """The paper's mission (paper-fig7) on `robots` robots: (the scenario file's text, its Scenario).

    Everything physical is read from paper-fig7.toml: each robot is the paper's camera robot (its
    platform, battery and sensors), `cameras` of them (default: all) keep the camera and the others
    carry laser and odometry only; robot rI runs the paper's Loc chain as Loc-I and, with a camera,
    its 4 Hz Blob chain as Blob-I; the base station, components, migration costs, accounting and
    network are the paper's, with `topology` planned (relay: r1, as in the paper; neighbours: every
    robot links to the base station and, standing in a ring, to its `neighbours` nearest robots on
    either side, so a robot's links do not grow with the team) and `media`, when given, the
    candidate media of every link (default: the paper's per link group). `seed` picks which robots
    carry the cameras when there are fewer cameras than robots.

    The text is checked by the project's loader before it is returned (the Scenario is what it
    loads to); bad input raises ScenarioError with one line saying what to give instead.
    """
    if isinstance(robots, bool) or not isinstance(robots, int) or robots < 1:
        raise ScenarioError(f"a fleet needs at least one robot: N must be >= 1, not {robots!r}")
    cameras = robots if cameras is None else cameras
    if isinstance(cameras, bool) or not isinstance(cameras, int) or not 0 <= cameras <= robots:
        raise ScenarioError(f"--cameras must be between 0 and the number of robots ({robots}), not {cameras!r}")
    if topology not in PAPER_FLEET_TOPOLOGIES:
        raise ScenarioError(f"unknown topology {topology!r}: one of {', '.join(PAPER_FLEET_TOPOLOGIES)}")
    if isinstance(neighbours, bool) or not isinstance(neighbours, int) or neighbours < 1:
        raise ScenarioError(f"--neighbours must be at least 1 (robots in range on either side), not {neighbours!r}")
    paper = load_toml((resources.files("autopower.scenarios") / "paper-fig7.toml").read_text(encoding="utf-8"),
                      "<built-in paper-fig7>")
    unknown = [m for m in media if m not in paper["radios"]]
    if unknown:
        raise ScenarioError(f"unknown medium {unknown[0]!r}: one of {', '.join(paper['radios'])} (the paper's radios)")
    camera_robot = next(r for r in paper["robots"] if "camera" in r.get("sensors", []))
    loc = next(c for c in paper["chains"] if c.get("component") == "Loc")
    blob = next(c for c in paper["chains"] if "camera" in c.get("requires", []))
    rng = np.random.default_rng([seed, robots, 0xCA3])
    with_camera = set(range(1, robots + 1)) if cameras == robots else {
        int(i) + 1 for i in rng.choice(robots, size=cameras, replace=False)}
    team, chains = [], []
    for i in range(1, robots + 1):
        sensors = [s for s in camera_robot["sensors"] if i in with_camera or s != "camera"]
        team.append({**camera_robot, "name": f"r{i}", "sensors": sensors})
        chains.append({**loc, "name": f"Loc-{i}", "source": f"r{i}"})
    chains += [{**blob, "name": f"Blob-{i}", "source": f"r{i}"} for i in sorted(with_camera)]
    network = dict(paper["network"], topology=topology, relay="r1")
    if media:
        network["laptop_robot_media"] = network["robot_robot_media"] = list(dict.fromkeys(media))
    used = {m for key in ("laptop_robot_media", "robot_robot_media") for m in network[key]}
    if topology == "neighbours":
        network = _neighbour_network(network, robots, neighbours, paper["basestation"]["name"])
    components = {c["component"] for c in chains}
    data: dict[str, Any] = {
        "scenario": {**paper["scenario"], "name": f"fleet-{robots}",
                     "description": f"{robots} robots on the paper's platforms, {cameras} with a camera: "
                                    f"a Loc chain each and a {1 / blob['period_s']:g} Hz Blob chain per camera ({topology})"},
        "platforms": paper["platforms"],
        "radios": {m: spec for m, spec in paper["radios"].items() if m in used},
        "basestation": paper["basestation"],
        "network": network,
    }
    if "migration" in paper:
        migration = dict(paper["migration"])
        if "state_bytes" in migration:
            migration["state_bytes"] = {k: v for k, v in migration["state_bytes"].items() if k in components}
        data["migration"] = migration
    data["components"] = {name: spec for name, spec in paper["components"].items() if name in components}
    data["robots"], data["chains"] = team, chains
    how = f"{robots} --cameras {cameras} --topology {topology}" + "".join(f" --medium {m}" for m in media)
    if topology == "neighbours":
        how += f" --neighbours {neighbours}"
    text = (f"# Generated by `autopower scenarios fleet {how} --seed {seed}` from paper-fig7:\n"
            f"# its platforms, radios, base station, components and chains, on {robots} robots.\n" + dumps_toml(data))
    return text, parse_scenario(text, f"<fleet of {robots}>")


def _neighbour_network(network: dict[str, Any], robots: int, neighbours: int, base: str) -> dict[str, Any]:
    """An explicit network: each robot to the base station (the laptop-robot group) and its ring
    neighbours (the robot-robot group), with the paper's candidate media per group."""
    up = [{"a": f"r{i}", "b": base, "media": network["laptop_robot_media"], "group": LAPTOP_ROBOT}
          for i in range(1, robots + 1)]
    ring = [{"a": f"r{i}", "b": f"r{j}", "media": network["robot_robot_media"], "group": ROBOT_ROBOT}
            for i, j in ring_links(robots, neighbours)]
    out = {k: v for k, v in network.items() if k not in ("laptop_robot_media", "robot_robot_media")}
    return {**out, "topology": "explicit", "analyze_topologies": ["explicit"], "links": up + ring}


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def dumps_toml(data: dict[str, Any]) -> str:
    """A scenario's TOML tree as text: each top-level table a [section], a table of tables one
    [section.NAME] per entry, an array of tables [[section]]s, deeper tables inline."""
    out: list[str] = []
    for name, value in data.items():
        if isinstance(value, list) and all(isinstance(v, dict) for v in value):
            for item in value:
                out += ["", f"[[{_key(name)}]]", *_pairs(item)]
        elif isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()):
            for entry, table in value.items():
                out += ["", f"[{_key(name)}.{_key(entry)}]", *_pairs(table)]
        elif isinstance(value, dict):
            out += ["", f"[{_key(name)}]", *_pairs(value)]
        else:
            raise ValueError(f"top-level {name!r} is not a table: {value!r}")
    return "\n".join(out).lstrip("\n") + "\n"


def _pairs(table: dict[str, Any]) -> list[str]:
    return [f"{_key(k)} = {_value(v)}" for k, v in table.items()]


def _key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"not a finite number: {value}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # JSON's escapes are all TOML escapes
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }" if value else "{}"
    raise ValueError(f"no TOML for {type(value).__name__} {value!r}")


__all__ = ["random_scenario", "loaded_fleet_scenario", "random_dag_scenario", "fleet_scenario", "paper_fleet",
           "dumps_toml", "PAPER_FLEET_TOPOLOGIES", "LAPTOP_ROBOT", "ROBOT_ROBOT", "LinkSpec", "Platform", "Radio"]
