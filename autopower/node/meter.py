"""Battery metering from real activity, with the energy model's prices.

What is charged, and why it reproduces `autopower.model.energy.evaluate` for the same allocation:
- CPU: ``idle_w`` for every virtual second, plus ``(busy_w - idle_w) * latency`` for every
  component run actually executed here, with the component's *modelled* latency on this
  node's platform (the paper's Sitsang/laptop profile, not this machine's). Runs at 1/period
  give the model's ``idle + (busy - idle) * sum(latency / period)``.
- Radios: every message actually sent / received / forwarded charges ``airtime * send_w``
  (or ``receive_w``) of the medium of the hop it crossed — the model's `airtime_s`, with the
  loss of the link to the peer it went to or came from (``[network] loss``: 1 / (1 - loss)
  times, the retransmissions) — times the chain's flow weight
  (`model.flow_weight`: under paper accounting one real message stands for ``period`` modelled
  ones). A node has one radio per medium among its links; each draws ``sleep_w`` for every
  virtual second it is not busy: sleep is charged for elapsed time and credited back for the
  busy airtime, which is the model's ``sleep_w * (1 - busy)``.
- Mains-powered nodes (the base station) pay nothing.
- DVFS (`model.dvfs`): at a frequency level the idle and busy power are the level's, and every run
  is charged the modelled latency times the level's latency factor (`set_level`, from the plan).

Work the model's steady state does not include is kept in parts of its own, so that a run can
be checked against the model and its overheads reported beside it: migrations (the state on
the radios) and recovery after a silent loss (resent frames; a stage restarted without state
recomputing inputs), the control plane's bytes, and the runtime's own CPU (`charge_runtime`): see
`autopower.model.parts`.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Iterable, Mapping

from autopower.model.energy import airtime_s
from autopower.model.parts import (
    CPU_BUSY,
    CPU_IDLE,
    CPU_RECOVERY,
    CPU_RUNTIME,
    OVERHEAD_KINDS,
    RUN_PARTS,
    overhead_kind,
    radio_part as part,
)
from autopower.model.scenario import Platform, Radio

__all__ = ["BatteryMeter", "CPU_BUSY", "CPU_IDLE", "CPU_RECOVERY", "part"]


def _finite(value) -> float:
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"not a finite number: {value!r}")
    return x


class BatteryMeter:
    """Energy consumed by one node, by part, as a function of virtual time."""

    def __init__(self, *, platform: Platform, radios: Mapping[str, Radio], initial_j: float | None,
                 t0: float, media: Iterable[str] = (), loss: Mapping[str, float] | None = None):
        self.platform = platform
        self.loss = dict(loss or {})  # peer -> the share of packets the link to it loses (`Scenario.link_loss`)
        self.nominal = platform  # the platform's own figures; `set_level` swaps in a level's
        self.level: str | None = None
        self.latency_factor = 1.0
        self.radios = dict(radios)
        self.mains = platform.mains
        self.initial_j = None if self.mains else float(initial_j)
        self.t = float(t0)
        self.t0 = float(t0)
        self.media: frozenset[str] = frozenset(media)
        self.energy_j: dict[str, float] = {}
        self.cpu_busy_s = 0.0  # modelled busy time, for utilisation
        self.runtime_cpu_s = 0.0  # the runtime's own CPU on this platform (`charge_runtime`): seconds busy
        self.airtime_s: dict[str, float] = {}  # weighted busy airtime per medium
        self._history: deque[tuple[float, dict[str, float], float]] = deque([(self.t, {}, 0.0)])

    # ---- time ------------------------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Charge idle CPU and sleeping radios up to virtual time ``t``."""
        dt = t - self.t
        if dt <= 0:
            return
        self.t = t
        if self.mains:
            return
        self._add(CPU_IDLE, self.platform.idle_w * dt)
        for medium in sorted(self.media):  # parts in one order: the total's float sum is then the same
            self._add(part(medium, "sleep"), self.radios[medium].sleep_w * dt)

    def set_media(self, media: Iterable[str], t: float) -> None:
        """The node's radios change (a new plan picked other media): charge up to now first."""
        self.advance(t)
        self.media = frozenset(media)

    def set_level(self, level, t: float) -> None:
        """Run at a DVFS level (a `model.dvfs.FrequencyLevel`; None: the platform's nominal figures)
        from virtual time t on: idle time up to t is charged at the previous level first."""
        if (level.name if level else None) == self.level:
            return
        self.advance(t)
        if level is None:
            self.platform, self.level, self.latency_factor = self.nominal, None, 1.0
        else:
            self.platform = dataclasses.replace(self.nominal, idle_w=level.idle_w, busy_w=level.busy_w)
            self.level, self.latency_factor = level.name, level.latency_factor

    # ---- activity ------------------------------------------------------------------------------
    def charge_run(self, latency_s: float, t: float, purpose: str = "chain") -> float:
        """Charge one run of modelled (nominal) latency; at a DVFS level it takes factor times longer.

        ``purpose``: ``"chain"`` (the plan's steady work), ``"recovery"`` or ``"backlog"``
        (`autopower.model.parts.RUN_PARTS`)."""
        self.advance(t)
        if self.mains:
            return 0.0
        latency_s *= self.latency_factor
        joules = (self.platform.busy_w - self.platform.idle_w) * latency_s
        self._add(RUN_PARTS[purpose], joules)
        self.cpu_busy_s += latency_s
        return joules

    def charge_runtime(self, host_cpu_s: float, t: float) -> float:
        """Charge the CPU the node's runtime (all but component code) used on the computer running it:
        on this platform that is ``slowdown`` times as many seconds busy (at a DVFS level, its
        latency factor times more). A platform without ``slowdown`` (or a mains-powered one) pays
        nothing: the figure is the status's ``runtime_cpu_s`` alone."""
        self.advance(t)
        slowdown = self.nominal.slowdown
        if self.mains or slowdown is None or host_cpu_s <= 0:
            return 0.0
        busy_s = host_cpu_s * slowdown * self.latency_factor
        joules = (self.platform.busy_w - self.platform.idle_w) * busy_s
        self._add(CPU_RUNTIME, joules)
        self.runtime_cpu_s += busy_s
        return joules

    def charge_radio(self, direction: str, medium: str, n_bytes: int, weight: float, t: float,
                     purpose: str = "chain", peer: str | None = None) -> float:
        """Charge one message sent (``direction="send"``) to ``peer`` or received from it over ``medium``
        (the link's loss priced as the model prices it; no peer: a lossless link)."""
        self.advance(t)
        if self.mains:
            return 0.0
        radio = self.radios[medium]
        busy = airtime_s(n_bytes, radio, self.loss.get(peer, 0.0)) * weight
        watts = radio.send_w if direction == "send" else radio.receive_w
        joules = watts * busy
        bucket = direction if purpose == "chain" else purpose  # "migration" | "recovery": overheads
        self._add(part(medium, bucket), joules)
        # A busy radio is not sleeping: credit back its sleep power for that airtime.
        self._add(part(medium, "sleep"), -radio.sleep_w * busy)
        self.airtime_s[medium] = self.airtime_s.get(medium, 0.0) + busy
        return joules

    def _add(self, key: str, joules: float) -> None:
        self.energy_j[key] = self.energy_j.get(key, 0.0) + joules

    # ---- readings ------------------------------------------------------------------------------
    @property
    def consumed_j(self) -> float:
        return sum(self.energy_j.values())

    def overhead_j(self) -> dict[str, float]:
        """Energy outside the model's steady state so far, by kind (migration, recovery)."""
        out = {kind: 0.0 for kind in OVERHEAD_KINDS}
        for name, joules in self.energy_j.items():
            kind = overhead_kind(name)
            if kind is not None:
                out[kind] += joules
        return out

    @property
    def battery_j(self) -> float | None:
        return None if self.mains else self.initial_j - self.consumed_j

    @property
    def depleted(self) -> bool:
        return not self.mains and self.battery_j <= 0

    def restore(self, saved: Mapping) -> None:
        """Carry on from what a crashed process metered (`NodeRuntime.resume_state`).

        Metered up to the saved time; the time the process was down is charged at the next
        `advance` as idle CPU with its radios asleep (the robot kept drawing current).
        """
        if not self.mains and saved.get("initial_j") is not None:
            self.initial_j = _finite(saved["initial_j"])
        self.energy_j = {str(k): _finite(v) for k, v in saved.get("energy_j", {}).items()}
        self.cpu_busy_s = _finite(saved.get("cpu_busy_s", 0.0))
        self.runtime_cpu_s = _finite(saved.get("runtime_cpu_s", 0.0))
        self.airtime_s = {str(k): _finite(v) for k, v in saved.get("airtime_s", {}).items()}
        self.t = min(_finite(saved.get("t_virtual", self.t)), self.t)
        self.media = frozenset(m for m in saved.get("media", ()) if m in self.radios)
        self._history = deque([self.snapshot()])

    def snapshot(self) -> tuple[float, dict[str, float], float]:
        return self.t, dict(self.energy_j), self.cpu_busy_s

    def window(self, t: float, span_s: float) -> tuple[dict[str, float], float]:
        """Mean power by part and modelled CPU utilisation over the last ``span_s`` virtual seconds."""
        self.advance(t)
        now = self.snapshot()
        self._history.append(now)
        while len(self._history) > 2 and self._history[1][0] <= t - span_s:
            self._history.popleft()
        t_old, parts_old, busy_old = self._history[0]
        dt = t - t_old
        if dt <= 0:
            return {}, 0.0
        power = {k: (v - parts_old.get(k, 0.0)) / dt for k, v in now[1].items()}
        return power, (now[2] - busy_old) / dt
