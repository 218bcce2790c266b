"""A node's status: what it sends the team with every status period (`NodeStatus`).

Built from what each of the runtime's collaborators owns: the meter's energies and power, the stages
hosted (`Hosting`), the sources (`Sources`), the sinks' ledgers (`Sinks`), the links in sight
(`Sight`), custody's and the holds' counts, the acknowledgements wanted (`Acknowledging`), the plan
and the model's power (`PlanView`), the time down and the sources resumed (`Resuming`), the process and the CPU and control-plane bytes
(`Metering`).
"""

from __future__ import annotations

from autopower.protocol import NodeStatus


def node_status(rt, window_s: float, queue_depth: int = 0, queue_wait_s: float = 0.0) -> NodeStatus:
    """``rt``'s status (a `NodeRuntime`): what its meter, stages, sources, sinks, custody and peers say now."""
    rt.metering.settle_relayed()
    now = rt.now()
    power, utilisation = rt.meter.window(now, window_s) if rt.meter else ({}, 0.0)
    sources = rt.feeds.stats()
    return NodeStatus(
        node=rt.node, t_virtual=now, t_unix=rt.wall(), plan_epoch=rt.plan.epoch if rt.plan else -1,
        initial_j=rt.meter.initial_j if rt.meter else None,
        battery_j=rt.meter.battery_j if rt.meter else None,
        energy_j=dict(rt.meter.energy_j) if rt.meter else {},
        power_w=power, cpu_utilisation=utilisation,
        hosted={n: h.lifecycle.value for n, h in rt.hosted.items()},
        sources=sources,
        sinks=rt.sinking.stats(),
        links=rt.sight.links(),
        runs={n: h.runs for n, h in rt.hosted.items() if h.runs},
        compute_ms={n: h.compute_s / h.runs * 1e3 for n, h in rt.hosted.items() if h.runs},
        queue_depth=queue_depth, errors=dict(rt.errors),
        counters={**rt.counters, "held-outputs": len(rt.holds), **rt.custody.stats()},
        depleted=bool(rt.meter and rt.meter.depleted),
        acks_wanted=tuple(sorted(rt.acknowledging.ack_interest())),
        failed=dict(rt.hosting.failed),
        plan_incarnation=rt.plan.incarnation if rt.plan else 0,
        plan_leader=rt.plan.leader if rt.plan else "",
        # for a base station that does not run our plan (one that restarted takes over the mission
        # with it, `basestation.takeover`); not in every status: it grows with the team (its
        # starting energies: 1.4 of a robot's 2.1 kB at 100 robots)
        mission=rt.mission if rt.sight.mission_wanted() else None,
        generations={n: h.generation for n, h in rt.hosted.items()},
        plan_operator=rt.plan.operator if rt.plan else None,
        model_w=rt.plan_view.model_w,
        down=rt.resuming.down,
        queue_wait_s=queue_wait_s,
        zid=rt.bus.zid,
        link_bytes=rt.control_plane.link_bytes(),
        link_packets=rt.control_plane.link_packets(),
        control_bytes=rt.control_plane.control_bytes(),
        runtime_cpu_s=rt.metering.runtime_cpu_s,
        component_cpu_s=rt.metering.component_cpu_s,
        process=rt.process,
        resumed=dict(rt.resuming.sources),
    )
