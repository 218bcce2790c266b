"""Metering beyond the chains' own work: what a node forwards on arrival, its control plane's bytes
and the runtime's own CPU.

`Metering` is a collaborator of `NodeRuntime`. It owns the CPU readings it charges from (the
process's and the component code's at the last reading) and the CPU the runtime and the component
code have used since the mission started in this process (`NodeStatus.runtime_cpu_s`,
``component_cpu_s``). It charges the runtime's `BatteryMeter`; the bytes per link are the
`ControlPlaneMeter`'s, the packets forwarded on arrival the `ArrivalRelay`'s.
"""

from __future__ import annotations


class Metering:
    """What the node's meter is charged for besides the chains' frames and runs."""

    def __init__(self, rt):
        """``rt``: the `NodeRuntime` whose meter this charges."""
        self.rt = rt
        self._cpu_at: tuple[float, float] | None = None  # (process, component) CPU at the last `charge_runtime`
        # since the mission started in this process, on the computer running it (`charge_runtime`):
        self.runtime_cpu_s = 0.0  # the runtime's CPU
        self.component_cpu_s = 0.0  # the component code's (runs, sources, state, constructors)

    def settle_relayed(self) -> None:
        """On the loop: charge the meter and count what was forwarded on arrival since last time."""
        if self.rt.meter is None:
            return  # (forwarded before the mission's meter exists: charged at the next call)
        n, slow = self.rt.arrivals.settle(self.rt.meter, self.rt.control_plane)
        if n:
            self.rt.tally("forwarded", n)
            self.rt.tally("forwarded-on-arrival", n)
        if slow:
            self.rt.tally("relay-congested", slow)

    def charge_control(self, by_zid: dict[str, tuple[int, int]],
                       packets_by_zid: dict[str, tuple[int, int]] | None = None) -> None:
        """The bytes each peer session exchanged with this node's so far (`LinkTraffic.poll`): what
        was not chain packets is charged to the radio of its link as the control plane's. Counted
        from the mission's start: before it, the totals only set where counting starts. And the
        packets (`LinkTraffic.packets_by_peer`), reported in the status (`link_packets`)."""
        if self.rt.meter is None:
            self.rt.control_plane.start_from(by_zid, packets_by_zid)
            return
        self.rt.control_plane.count_packets(packets_by_zid or {})
        unpriced = self.rt.control_plane.charge(by_zid, self.rt.meter, self._medium_to, self.rt.now())
        if unpriced:
            self.rt.tally("control-bytes-unpriced", unpriced)

    def charge_runtime(self, process_cpu_s: float) -> None:
        """The CPU this node's process has used so far (``time.process_time``, every thread: the loop,
        Zenoh's, the guard's): what its component code did not use (`GuardedCalls.component_cpu_s`)
        is the runtime's, charged through the platform's ``slowdown`` (`BatteryMeter.charge_runtime`).
        Counted from the mission's start: before it, the readings only set where counting starts."""
        reading = (process_cpu_s, self.rt.guard.component_cpu_s)
        last, self._cpu_at = self._cpu_at, reading
        if self.rt.meter is None or last is None:
            return
        components = max(0.0, reading[1] - last[1])
        runtime = max(0.0, (reading[0] - last[0]) - components)  # a call's CPU counted late can make it dip
        self.component_cpu_s += components
        self.runtime_cpu_s += runtime
        self.rt.meter.charge_runtime(runtime, self.rt.now())

    def _medium_to(self, peer: str) -> str | None:
        """The radio this node talks to ``peer`` on: its plan's link, else its only radio."""
        network = self.rt.plan_view.network
        medium = network.medium_between(self.rt.node, peer) if network is not None else None
        if medium is None and self.rt.meter is not None and len(self.rt.meter.media) == 1:
            (medium,) = self.rt.meter.media
        return medium
