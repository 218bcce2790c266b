"""The AutoPower energy model: power, utilisation and lifetime of an allocation.

Rules (docs/concepts/energy-model.md; they reproduce the paper's Fig. 7 exactly):
- CPU power = idle_w + (busy_w - idle_w) * u, u = sum(latency / period) of hosted stages.
- A message of n bytes occupies its medium for n*8 / (kbps*1024) s, times 1 / (1 - loss) on a
  link the scenario says loses that share of its packets (`airtime_s`; no loss: the paper); on
  every hop the sender pays send_w for that airtime and the receiver receive_w (a relay pays
  both); the base station pays nothing (mains).
- A node has one radio per medium among its links; each draws sleep_w * (1 - busy) plus its
  send/receive energy. u > 1 or busy > 1 makes an allocation infeasible.
- Lifetime = min over robots of energy / power, rounded to the nearest multiple of the
  scenario's 0.8 s, halves up (`round_lifetime`); the raw value is kept beside it.
- "paper" accounting charges every flow one message per second (the paper's quirk);
  "physical" charges 1/period messages per second.

Loads (utilisation and airtime) add up chain by chain, so they are vectors; `LoadSpace.power`
turns a batch of load vectors into power, and both `evaluate` and the planners use it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from decimal import ROUND_HALF_UP, Decimal
from typing import Mapping, Sequence

import numpy as np

from autopower.errors import ScenarioError
from autopower.model.dag import Flow, active_flows, chain_of_stage, runnable
from autopower.model.network import Network
from autopower.model.scenario import Chain, Radio, Scenario

UTILISATION_LIMIT = 1.0 + 1e-9  # float noise must not flip a 100 %-utilised plan to infeasible


def airtime_s(n_bytes: int, radio: Radio, loss: float = 0.0) -> float:
    """Seconds one message of n_bytes occupies the radio (the paper's kbit = 1024 bit), over a link
    that loses the share ``loss`` of its packets (`Scenario.link_loss`; 0: the paper's model).

    A retransmitting transport (TCP, QUIC: Zenoh's reliable links) sends each packet until it
    arrives: 1 / (1 - loss) times on average, and each lost copy kept the sender's radio and the
    receiver's busy all the same. So the message's airtime, and with it the send and the receive
    energy of the hop, is multiplied by `transmissions(loss)`. bench/bench_lossy_links.py measures
    it on the testbed: the bytes a link really carries per byte delivered, at 5-20 % loss, over
    TCP and QUIC, against the same link without loss (docs/concepts/energy-model.md).

    Every price of a message on a hop goes through here: the evaluator's `LoadSpace.flow_load`
    (so the exhaustive planner), the MILP's hop terms (`planner/milp.py`), the live meter
    (`node.meter`), migrations (`policies.team`); a caller that knows the hop gives its loss.
    `planner/repair.py`'s own bound without it stays a valid, looser, lower bound (a loss only
    adds power).
    """
    air = n_bytes * 8.0 / (radio.kbps * 1024.0)
    return air * transmissions(loss) if loss else air


def transmissions(loss: float) -> float:
    """Expected transmissions per delivered packet on a link losing the share ``loss`` (0 <= loss < 1)."""
    if not 0.0 <= loss < 1.0:
        raise ScenarioError(f"link loss {loss!r} is not a share of packets in [0, 1); give e.g. 0.1 for 10 %")
    return 1.0 / (1.0 - loss)


def flow_rate_hz(chain: Chain, accounting: str) -> float:
    """Modelled messages per second on each flow of a chain."""
    return 1.0 if accounting == "paper" else 1.0 / chain.period_s


def flow_weight(chain: Chain, accounting: str) -> float:
    """How many modelled messages one real message stands for (a runtime sends 1/period a second).

    Under paper accounting a 2 s chain's real message is charged as 2, a 0.25 s one as 0.25,
    so that a metering runtime reproduces the model's one-message-per-second rule.
    """
    return flow_rate_hz(chain, accounting) * chain.period_s


def round_lifetime(lifetime_s: float, quantum_s: float) -> float:
    """The nearest multiple of quantum_s; a lifetime exactly halfway rounds up (away from zero).

    The division is done in decimal on the numbers as written (repr), so a half stays a half:
    2.0 s to 0.8 s is 2.5 quanta -> 2.4 s (binary floats would see 2.4999... and Python's
    `round` would send halves to the even multiple). quantum_s <= 0 means no rounding.
    """
    if quantum_s <= 0 or not np.isfinite(lifetime_s):
        return lifetime_s
    quanta = (Decimal(repr(float(lifetime_s))) / Decimal(repr(float(quantum_s)))).quantize(
        Decimal(1), rounding=ROUND_HALF_UP)
    return float(quanta * Decimal(repr(float(quantum_s))))


# ---------------------------------------------------------------------------------------------
# Loads and power
# ---------------------------------------------------------------------------------------------


class LoadSpace:
    """Index layout of load vectors on one network, and the load -> power arithmetic.

    A load vector holds, per node, CPU utilisation, then per (node, medium) send airtime per
    second and receive airtime per second.
    """

    def __init__(self, scenario: Scenario, network: Network, accounting: str, energies_j: Mapping[str, float]):
        self.scenario = scenario
        self.network = network
        self.accounting = accounting
        self.nodes = list(network.nodes)
        self.robots = [n for n in self.nodes if n != network.basestation]
        self.media = list(scenario.radios)
        self.node_index = {n: i for i, n in enumerate(self.nodes)}
        self.medium_index = {m: i for i, m in enumerate(self.media)}
        n, m = len(self.nodes), len(self.media)
        self.size = n + 2 * n * m
        self._send0, self._recv0 = n, n + n * m
        self.robot_rows = np.array([self.node_index[r] for r in self.robots], dtype=int)
        # Nodes whose radios may be at most 100 % busy: the robots, and the base station too when
        # the scenario limits its radios (off by default: the paper leaves them unlimited).
        limited = self.robots + ([network.basestation] if scenario.basestation_radio_limit
                                 and network.basestation in self.node_index else [])
        self.radio_limited_rows = np.array([self.node_index[n] for n in limited], dtype=int)
        self.energy_j = np.array([float(energies_j[r]) for r in self.robots])
        platforms = [scenario.platform_of(r) for r in self.robots]
        self.idle_w = np.array([p.idle_w for p in platforms])
        self.busy_extra_w = np.array([p.busy_w - p.idle_w for p in platforms])
        radios = [scenario.radios[k] for k in self.media]
        self.sleep_w = np.array([r.sleep_w for r in radios])
        self.send_w = np.array([r.send_w for r in radios])
        self.receive_w = np.array([r.receive_w for r in radios])
        self.present = np.zeros((len(self.robots), m), dtype=bool)
        for i, robot in enumerate(self.robots):
            for medium in network.media_of(robot):
                self.present[i, self.medium_index[medium]] = True
        self._chain_cache: dict[tuple[str, tuple[str, ...]], np.ndarray] = {}
        # the team's own statuses and keep-alives on every link (`model.control_plane`): the same
        # whatever runs where, so every load of this space carries it (`split`); None when off
        self.control = self._control_load() if scenario.control_plane.enabled else None

    def _control_load(self) -> np.ndarray:
        load = np.zeros(self.size)
        for (u, v), n_bytes in self.scenario.control_plane.directed_bytes(self.network).items():
            medium = self.network.medium_between(u, v)
            air = airtime_s(n_bytes, self.scenario.radios[medium], self.scenario.link_loss(u, v))
            load[self.send_slot(u, medium)] += air
            load[self.recv_slot(v, medium)] += air
        return load

    def cpu_slot(self, node: str) -> int:
        return self.node_index[node]

    def send_slot(self, node: str, medium: str) -> int:
        return self._send0 + self.node_index[node] * len(self.media) + self.medium_index[medium]

    def recv_slot(self, node: str, medium: str) -> int:
        return self._recv0 + self.node_index[node] * len(self.media) + self.medium_index[medium]

    def flow_load(self, src: str, dst: str, n_bytes: int, rate_hz: float, out: np.ndarray) -> None:
        for u, v, medium in self.network.route(src, dst):
            air = airtime_s(n_bytes, self.scenario.radios[medium], self.scenario.link_loss(u, v)) * rate_hz
            out[self.send_slot(u, medium)] += air
            out[self.recv_slot(v, medium)] += air

    def chain_load(self, chain: Chain, hosts: tuple[str, ...]) -> np.ndarray:
        """Load of one chain with its stages on `hosts` (cached: planners call it a lot)."""
        key = (chain.name, hosts)
        cached = self._chain_cache.get(key)
        if cached is not None:
            return cached
        load = np.zeros(self.size)
        for stage, host in zip(chain.stages, hosts, strict=False):
            latency = self.scenario.components[stage.component].latency_s[self.scenario.platform_of(host).name]
            load[self.cpu_slot(host)] += latency / chain.period_s
        rate = flow_rate_hz(chain, self.accounting)
        hops = (chain.source, *hosts, chain.sink)
        for (src, dst), n_bytes in zip(zip(hops, hops[1:], strict=False), chain.message_bytes, strict=False):
            if src != dst:
                self.flow_load(src, dst, n_bytes, rate, load)
        self._chain_cache[key] = load
        return load

    def dag_flow_load(self, flow: Flow, producer_chain: Chain, src: str, dst: str) -> np.ndarray:
        """Load of one DAG flow (autopower.model.dag) from its producer's host to its consumer's.

        Between hosts with no route (a partitioned team) it carries nothing: its frames wait in
        their producer's custody until a route returns, as a chain's results wait for its sink."""
        key = (flow.name, (src, dst))
        cached = self._chain_cache.get(key)
        if cached is None:
            cached = np.zeros(self.size)
            if src != dst and self.network.reachable(src, dst):
                self.flow_load(src, dst, flow.n_bytes, flow_rate_hz(producer_chain, self.accounting), cached)
            self._chain_cache[key] = cached
        return cached

    # ---- load -> power -------------------------------------------------------------------------
    def split(self, loads: np.ndarray):
        """(cpu_u (K,N), send_air (K,N,M), recv_air (K,N,M)) of a (K, size) batch, the control
        plane's load added when the scenario charges it."""
        if self.control is not None:
            loads = loads + self.control
        k = loads.shape[0]
        n, m = len(self.nodes), len(self.media)
        cpu = loads[:, :n]
        send = loads[:, self._send0:self._recv0].reshape(k, n, m)
        recv = loads[:, self._recv0:].reshape(k, n, m)
        return cpu, send, recv

    def breakdown(self, loads: np.ndarray) -> dict[str, np.ndarray]:
        """Per robot power parts for a batch of loads: cpu_w (K,R); send/receive/sleep_w (K,R,M)."""
        cpu, send, recv = self.split(loads)
        rows = self.robot_rows
        u = cpu[:, rows]
        send_r, recv_r = send[:, rows, :], recv[:, rows, :]
        busy = send_r + recv_r
        return {
            "cpu_u": u,
            "cpu_w": self.idle_w + self.busy_extra_w * u,
            "send_w": send_r * self.send_w,
            "receive_w": recv_r * self.receive_w,
            "sleep_w": self.present * self.sleep_w * np.clip(1.0 - busy, 0.0, None),
            "busy": busy,
        }

    def control_w(self, robot: str) -> float:
        """What the control plane's airtime costs ``robot`` beyond its radios' sleep power (0 when off)."""
        if self.control is None:
            return 0.0
        send = self.control[[self.send_slot(robot, m) for m in self.media]]
        recv = self.control[[self.recv_slot(robot, m) for m in self.media]]
        return float(send @ (self.send_w - self.sleep_w) + recv @ (self.receive_w - self.sleep_w))

    def feasible(self, loads: np.ndarray) -> np.ndarray:
        return self.peak_utilisation(loads) <= UTILISATION_LIMIT

    def peak_utilisation(self, loads: np.ndarray) -> np.ndarray:
        """Per load row, the most loaded limited resource (CPU of any node, a limited radio)."""
        cpu, send, recv = self.split(loads)
        busy = (send + recv)[:, self.radio_limited_rows, :]
        peak = cpu.max(axis=1)
        if busy.size:
            peak = np.maximum(peak, busy.max(axis=(1, 2)))
        return peak

    def total_power(self, loads: np.ndarray) -> np.ndarray:
        parts = self.breakdown(loads)
        return parts["cpu_w"] + (parts["send_w"] + parts["receive_w"] + parts["sleep_w"]).sum(axis=2)

    def lifetimes(self, loads: np.ndarray) -> np.ndarray:
        """Raw team lifetime per load row; -inf where infeasible."""
        life = (self.energy_j / self.total_power(loads)).min(axis=1)
        return np.where(self.feasible(loads), life, -np.inf)


# ---------------------------------------------------------------------------------------------
# Evaluation of one allocation
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class RadioPower:
    medium: str
    send_w: float
    receive_w: float
    sleep_w: float
    busy: float  # fraction of each second the radio is sending or receiving

    @property
    def total_w(self) -> float:
        return self.send_w + self.receive_w + self.sleep_w


@dataclass(frozen=True, kw_only=True)
class RobotPower:
    robot: str
    energy_j: float
    cpu_w: float
    cpu_utilisation: float
    radios: Mapping[str, RadioPower]
    total_w: float
    lifetime_s: float
    # of total_w, what the control plane's airtime costs beyond the radios' sleep (0 when not charged)
    control_w: float = 0.0

    @property
    def steady_w(self) -> float:
        """The model's power without the control plane: what a live robot's metered steady state
        is compared with (the meter counts the control plane it measures among the overheads)."""
        return self.total_w - self.control_w


@dataclass(frozen=True, kw_only=True)
class Violation:
    node: str
    resource: str  # "cpu" or "radio:<medium>"
    value: float
    limit: float

    @property
    def message(self) -> str:
        return (f"{self.node} {self.resource} utilisation {self.value:.1%} exceeds {self.limit:.0%} "
                f"(by {(self.value - self.limit) * 100:.1f} points)")

    def to_dict(self) -> dict:
        return {"node": self.node, "resource": self.resource, "value": self.value, "limit": self.limit,
                "excess": self.value - self.limit, "message": self.message}


@dataclass(frozen=True, kw_only=True)
class Evaluation:
    accounting: str
    allocation: Mapping[str, str]
    network: Network
    robots: Mapping[str, RobotPower]
    utilisation: Mapping[str, float]  # CPU utilisation of every node, the base station too
    violations: tuple[Violation, ...]
    bottleneck: str | None
    basestation_radio_busy: Mapping[str, float] = dataclasses.field(default_factory=dict)  # medium -> busy
    lifetime_s: float | None  # raw; None when infeasible
    lifetime_rounded_s: float | None

    @property
    def feasible(self) -> bool:
        return not self.violations

    def to_dict(self) -> dict:
        return {
            "accounting": self.accounting,
            "allocation": dict(self.allocation),
            "feasible": self.feasible,
            "lifetime_s": self.lifetime_rounded_s,
            "lifetime_raw_s": self.lifetime_s,
            "bottleneck": self.bottleneck,
            "violations": [v.message for v in self.violations],
            "robots": {
                name: {
                    "energy_j": rp.energy_j,
                    "total_w": rp.total_w,
                    "cpu_w": rp.cpu_w,
                    "cpu_utilisation": rp.cpu_utilisation,
                    "lifetime_s": rp.lifetime_s,
                    "control_w": rp.control_w,
                    "radios": {m: {"send_w": r.send_w, "receive_w": r.receive_w, "sleep_w": r.sleep_w,
                                   "busy": r.busy} for m, r in rp.radios.items()},
                }
                for name, rp in self.robots.items()
            },
        }


def active_chains(scenario: Scenario, network: Network, disabled: frozenset[str] = frozenset()) -> list[Chain]:
    """Chains that run: not disabled by the operator and whose source robot is in the network."""
    return runnable([c for c in scenario.chains if c.name not in disabled and c.source in network.nodes])


def check_allocation(scenario: Scenario, network: Network, chains: Sequence[Chain], allocation: Mapping[str, str]) -> None:
    stages = {s.name: s for c in chains for s in c.stages}
    missing = [s for s in stages if s not in allocation]
    if missing:
        raise ScenarioError(f"allocation places no host for {', '.join(missing)}")
    for stage_name, host in allocation.items():
        if stage_name not in stages:
            raise ScenarioError(f"allocation names unknown or inactive stage {stage_name!r}; "
                                f"active stages: {', '.join(stages)}")
        if host not in network.nodes:
            raise ScenarioError(f"allocation puts {stage_name} on unknown or unavailable node {host!r}; "
                                f"nodes: {', '.join(network.nodes)}")


def load_of(space: LoadSpace, chains: Sequence[Chain], allocation: Mapping[str, str]) -> np.ndarray:
    total = np.zeros(space.size)
    for chain in chains:
        total += space.chain_load(chain, tuple(allocation[s.name] for s in chain.stages))
    return total + dag_load(space, chains, allocation)


def dag_load(space: LoadSpace, chains: Sequence[Chain], allocation: Mapping[str, str],
             flows: Sequence[Flow] | None = None) -> np.ndarray:
    """Load of the DAG flows between running `chains` (all of them, or just `flows`)."""
    total = np.zeros(space.size)
    if not flows and (flows is not None or not any(c.inputs for c in chains)):
        return total  # linear chains only: the common case stays as cheap as before
    by_stage = {**chain_of_stage(space.scenario.chains), **chain_of_stage(chains)}  # a flow's producer may be fixed
    for flow in active_flows(chains) if flows is None else flows:
        total += space.dag_flow_load(flow, by_stage[flow.producer], allocation[flow.producer],
                                     allocation[flow.consumer])
    return total


def evaluate(
    scenario: Scenario,
    network: Network,
    allocation: Mapping[str, str],
    accounting: str | None = None,
    energies_j: Mapping[str, float] | None = None,
    disabled_chains: frozenset[str] = frozenset(),
) -> Evaluation:
    """Power, utilisation, feasibility and lifetime of one allocation on one network."""
    accounting = accounting or scenario.accounting
    energies = {**scenario.energies_j(), **(energies_j or {})}
    chains = active_chains(scenario, network, disabled_chains)
    check_allocation(scenario, network, chains, allocation)
    space = LoadSpace(scenario, network, accounting, energies)
    load = load_of(space, chains, allocation)[None, :]
    parts = {k: v[0] for k, v in space.breakdown(load).items()}
    cpu_u, send_air, recv_air = (x[0] for x in space.split(load))

    violations = []
    for node in space.nodes:
        u = float(cpu_u[space.node_index[node]])
        if u > UTILISATION_LIMIT:
            violations.append(Violation(node=node, resource="cpu", value=u, limit=1.0))
    robots = {}
    for i, robot in enumerate(space.robots):
        radios = {}
        for j, medium in enumerate(space.media):
            if not space.present[i, j]:
                continue
            busy = float(parts["busy"][i, j])
            if busy > UTILISATION_LIMIT:
                violations.append(Violation(node=robot, resource=f"radio:{medium}", value=busy, limit=1.0))
            radios[medium] = RadioPower(medium=medium, send_w=float(parts["send_w"][i, j]),
                                        receive_w=float(parts["receive_w"][i, j]),
                                        sleep_w=float(parts["sleep_w"][i, j]), busy=busy)
        total = float(parts["cpu_w"][i] + sum(r.total_w for r in radios.values()))
        robots[robot] = RobotPower(robot=robot, energy_j=space.energy_j[i], cpu_w=float(parts["cpu_w"][i]),
                                   cpu_utilisation=float(parts["cpu_u"][i]), radios=radios, total_w=total,
                                   lifetime_s=space.energy_j[i] / total, control_w=space.control_w(robot))
    base_radios = {}
    if space.network.basestation in space.node_index:
        b = space.node_index[space.network.basestation]
        for medium in sorted(space.network.media_of(space.network.basestation), key=space.medium_index.get):
            j = space.medium_index[medium]
            busy = float(send_air[b, j] + recv_air[b, j])
            base_radios[medium] = busy
            if scenario.basestation_radio_limit and busy > UTILISATION_LIMIT:
                violations.append(Violation(node=space.network.basestation, resource=f"radio:{medium}",
                                            value=busy, limit=1.0))
    feasible = not violations
    bottleneck = min(robots, key=lambda r: robots[r].lifetime_s) if robots else None
    lifetime = robots[bottleneck].lifetime_s if (feasible and bottleneck) else None
    return Evaluation(
        accounting=accounting,
        allocation=dict(allocation),
        network=network,
        robots=robots,
        utilisation={n: float(cpu_u[space.node_index[n]]) for n in space.nodes},
        violations=tuple(violations),
        basestation_radio_busy=base_radios,
        bottleneck=bottleneck if feasible else (violations[0].node if violations else None),
        lifetime_s=lifetime,
        lifetime_rounded_s=round_lifetime(lifetime, scenario.lifetime_rounding_s) if lifetime else None,
    )
