"""A one-way failure on the testbed: out of reach for both ends, and nothing asymmetric after the heal.

Issue 31, item 3. `autopower fault cut A B --one-way` drops the packets A sends B (an nftables rule in
B's namespace) while B's packets still reach A: one end hears the other, which does not hear it.
Zenoh runs one transport (one TCP connection, mutual TLS) per pair, so a one-way cut must end as
a link out of reach for *both* ends (the deaf end's lease expires, and its close crosses the
direction that still works), the pair's traffic taking a relay meanwhile; after `fault heal` both
ends must see each other again, and every other node as well.

Needs root and nftables' `nft` (CI runs as root); without them these tests fail with that reason.
Every namespace a run creates is removed, also on failure (`clean`). Every wait has a deadline.

What the test reads, from the base station's snapshot (`autopower status --json`):

- the base station's own direct sight: its status's `links` (`basestation.links.r1`: r1's
  liveliness token is visible there), and `links_down`, the links the base station plans around;
- r1's direct sight: r1's status (`robots.r1.status.links.laptop`), which reaches the base station
  through a relay while the link is cut; r1 builds it as soon as its sight changes (the agent
  publishes at once on a change: `Agent._sight`), so its `t_unix` dates r1's view;
- each node's hosted stages (`hosted`: stage -> lifecycle) and each chain's sink (`sinks`).

After the heal every node must see every other within two leases. The cut closes the laptop-r1
session; the base station (the connecting end of that pair: later in the scenario's node order)
tries to reconnect at once, and while the link is down that attempt's SYNs are lost. With the
kernel's default (SYNs 1, 2, 3, 4, 5 and 7 s after the attempt began, then Zenoh's open timeout
at 10 s) a heal between two of them was seen at the next: 2.36 to 2.95 s after a heal with the
cut below. The testbed sets `net.ipv4.tcp_syn_linear_timeouts = 10` in every namespace (a SYN
every second), as a real team's nodes should (docs/deploying/robots.md).

The snapshot is taken in this process through the operator's mutual-TLS session to the base
station (what `autopower status` does), every 0.1 s: a CLI invocation costs 0.5 to 1 s on the
2-core CI machine, too coarse to time sub-second reactions.
"""

from __future__ import annotations

import json
import signal
import time

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.basestation.operator import OperatorClient
from autopower.basestation.process import BaseStationConfig
from autopower.cli.operator import operator_session_settings
from autopower.errors import AutoPowerError
from tests.e2e.test_testbed import clean, root, start_testbed, stop  # noqa: F401 - fixtures
from tests.e2e.test_up import run_cli, wait_until
from tests.integration.runtime_helpers import sinks_of
from tests.integration.test_testbed_loss import nft  # noqa: F401 - fixture

pytestmark = pytest.mark.slow

# The lease `testbed up` uses by default (1000 ms), given explicitly so the bounds below do not
# move with a default. Not the 500 ms of `autopower up`: on the shared 2-core CI machine a 500 ms
# lease expires on its own under load now and then (see test_testbed.py), which would turn a
# timing assertion into a coin toss; and a user of the testbed gets 1000 ms.
LEASE_S = 1.0
STATUS_PERIOD_S = 0.5  # the agents' and the base station's status period (`TeamSpec.status_period_s`)
# TCP gives up on data that stays unacknowledged after about 1.4 s in the testbed's namespaces
# (`autopower.launch.netns.TCP_RETRIES2` = 2 retransmissions from a 200 ms RTO: 0.2 + 0.4 + 0.8).
TCP_GIVE_UP_S = 1.4
SUSPECT_SETTLE_S = BaseStationConfig.suspect_settle_s  # the base station waits this before deciding
HEAL_HOLD_S = CoordinatorConfig.heal_hold_s  # a link back counts for plans after this long up

# Bounds, each from the mechanism, not from a run:
#
# - the end that no longer hears its peer drops it when its Zenoh lease expires: at most one lease
#   after the last keep-alive it received, which left before the cut: <= LEASE_S;
# - the other end (it still hears) drops it when the deaf end closes the transport: the close
#   crosses the direction that works at once, unless the deaf end's writer is stuck on a full
#   socket buffer (a peer that acknowledges nothing), which TCP ends after TCP_GIVE_UP_S;
# so both ends are out of each other's direct sight within
SIGHT_LOST_S = LEASE_S + TCP_GIVE_UP_S
# - the base station counts the link down (its `faults` record, `links_down`) on the first of: its
#   own sight lost (then `SUSPECT_SETTLE_S` to learn whether a relay still reaches r1) or r1's
#   report that it lost sight, which crosses the relay within a status period:
DECIDED_S = LEASE_S + max(SUSPECT_SETTLE_S, STATUS_PERIOD_S)
# - after the heal, each end reconnects: Zenoh retries a lost peer every 500 ms at most
#   (`ZenohSettings.retry_max_ms`), and the TCP and TLS handshakes take a few round trips; the
#   issue asks for every node to see every other within two leases:
SIGHT_BACK_S = 2 * LEASE_S
# - `links_down` empties once the link has been up for HEAL_HOLD_S (2 s: the coordinator's guard
#   against a flapping link; longer only for a link that went down again lately, which this one,
#   cut once, did not: `LinkStates`): that long after the base station saw r1 again, and a status
#   period
LINK_BACK_AFTER_SIGHT_S = HEAL_HOLD_S + STATUS_PERIOD_S
# How long the cut lasts, a robot behind an obstacle for a few seconds: 8 s, so that the heal comes
# when the base station's attempt to reconnect (begun when it lost r1, about a lease after the
# cut) is past TCP's linear SYN retransmissions, in the backed-off phase (see the module's
# docstring). A heal must not depend on how long the cut lasted; at this length, with the kernel's
# default SYN timing, it did.
CUT_S = 8.0
# What a reconnection may wait at worst (the waits' deadlines, not the bound): Zenoh's open timeout
# (`transport/unicast/open_timeout`, 10 s), then a retry
ZENOH_OPEN_TIMEOUT_S = 10.0
POLL_S = 0.1

NODES = ("laptop", "r1", "r2", "r3")
INSTANCE = ("starting", "running")  # lifecycles in which a stage's instance takes inputs


def views(snap: dict) -> dict[str, dict]:
    """Every node's last status: node -> its status dict (the base station's own included)."""
    out = {name: info["status"] for name, info in snap["robots"].items() if info.get("status")}
    if snap.get("basestation"):
        out["laptop"] = snap["basestation"]
    return out


def instances(snap: dict) -> dict[str, set[str]]:
    """Stage -> the nodes that report an instance of it that takes inputs."""
    out: dict[str, set[str]] = {stage: set() for stage in snap["placement"]}
    for node, status in views(snap).items():
        for stage, state in status["hosted"].items():
            if state in INSTANCE:
                out.setdefault(stage, set()).add(node)
    return out


def check_placement(snap: dict, settled: bool) -> None:
    """No stage's instance runs on two nodes; settled: each runs exactly where the placement says."""
    running = instances(snap)
    twice = {stage: sorted(nodes) for stage, nodes in running.items() if len(nodes) > 1}
    assert not twice, f"stages hosted twice: {twice}"
    if settled and not snap["migrating"]:
        assert all(running[stage] == {host} for stage, host in snap["placement"].items()), \
            (snap["placement"], running)


def check_sinks(snap: dict, before: dict) -> None:
    """No chain's sink ever took an output twice, none restarted or gave up on an output."""
    for chain, sink in sinks_of(snap).items():
        assert sink["duplicates_total"] == 0, (chain, sink)
        if chain in before:
            assert sink["run"] == before[chain]["run"], f"{chain} restarted: {before[chain]} -> {sink}"
            assert sink["given_up_total"] == before[chain]["given_up_total"], (chain, before[chain], sink)


def full_sight(snap: dict, after: float) -> bool:
    """Every node sees every other directly, by statuses each built after ``after``."""
    seen = views(snap)
    return set(seen) == set(NODES) and all(
        st["t_unix"] > after and all(st["links"].get(peer) for peer in NODES if peer != node)
        for node, st in seen.items())


def gap_free(snap: dict) -> bool:
    sinks = sinks_of(snap)
    return len(sinks) == 5 and all(s["received"] > 0 and s["contiguous"] == s["max_seq"] + 1 for s in sinks.values())


class Watcher:
    """Snapshots of the base station, polled every `POLL_S`, each checked as it comes.

    A snapshot is dated by the base station's own status in it (`basestation.t_unix`, built when
    the snapshot was): a change first seen in a snapshot happened after the one before it was taken
    and before it, so `until` gives both dates.
    """

    def __init__(self, session: dict):
        connect = tuple(session["connect"])
        self.client = OperatorClient(session["team"], connect=connect,
                                     settings=operator_session_settings(session, connect))
        self.sinks_before: dict = {}
        self.last: dict = {}
        self.taken = 0.0  # when the last snapshot was taken (base station's clock)

    def close(self) -> None:
        self.client.close()

    def snap(self) -> dict:
        try:
            snap = self.client.snapshot(timeout_s=3.0)
        except AutoPowerError:  # a loaded machine: the next poll tries again (every wait has a deadline)
            return {}
        check_placement(snap, settled=False)
        check_sinks(snap, self.sinks_before)
        self.last = snap
        self.taken = (snap.get("basestation") or {}).get("t_unix") or time.time()
        return snap

    def until(self, predicate, timeout_s: float, what: str):
        """(the first snapshot for which ``predicate`` is truthy, its value, (when the snapshot before
        it was taken, when it was taken)): what the predicate waits for happened in between."""
        def probe():
            before = self.taken
            snap = self.snap()
            if not snap:
                return None
            value = predicate(snap)
            return value and (snap, value, (before, self.taken))

        try:
            return wait_until(lambda: probe() or time.sleep(POLL_S), timeout_s, what)
        except AssertionError as exc:
            raise AssertionError(f"{exc}; last snapshot: links_down={self.last.get('links_down')} "
                                 f"sight={ {n: s['links'] for n, s in views(self.last).items()} if self.last else None}"
                                 ) from None


def status_of(snap: dict, node: str) -> dict | None:
    return views(snap).get(node)


@pytest.mark.parametrize("sender,receiver", [("r1", "laptop"), ("laptop", "r1")],
                         ids=["r1-not-heard-by-laptop", "laptop-not-heard-by-r1"])
def test_a_one_way_cut_is_out_of_reach_both_ways_and_heals_symmetric(tmp_path, clean, nft, sender, receiver):  # noqa: F811
    proc, session, env = start_testbed(tmp_path, "--lease-ms", str(int(LEASE_S * 1000)))
    watch = None
    try:
        watch = Watcher(session)
        # steady first: every node sees every other, every stage runs where placed, every sink gap-free
        steady, _, _ = watch.until(lambda s: s["ready"] and not s["links_down"] and full_sight(s, 0.0)
                                   and gap_free(s) and all(len(n) == 1 for n in instances(s).values()),
                                   30, "the team steady (full sight, every stage running, sinks gap-free)")
        check_placement(steady, settled=True)
        watch.sinks_before = sinks_of(steady)
        before = len(steady["faults"])

        result = run_cli(["fault", "cut", sender, receiver, "--one-way", "--json"], env)
        assert result.returncode == 0, result.stderr
        fault = json.loads(result.stdout)["fault"]
        assert fault["direction"] == f"{sender}->{receiver}", fault
        t_cut = fault["t_unix"]

        # (a) the base station: r1 out of its direct sight, the link counted down, r1 still in the team
        # (reached through a relay, which carries its statuses: below)
        def base_lost(s):
            return (not s["basestation"]["links"]["r1"] and ["laptop", "r1"] in s["links_down"]
                    and s["robots"]["r1"]["present"])

        _, _, (_, base_lost_by) = watch.until(base_lost, SIGHT_LOST_S + 5, "the base station to lose r1 directly")

        def handled(s):  # the link's fault record, once the team was reconfigured around it
            return next((f for f in s["faults"][before:] if f["kind"] == "link-down" and f["target"] == "laptop-r1"
                         and f["reconfigured_unix"]), None)

        _, record, _ = watch.until(handled, 10, "the link's fault to be handled")
        assert [f["target"] for f in watch.last["faults"][before:]] == ["laptop-r1"], watch.last["faults"][before:]
        # (b) r1: the laptop out of its direct sight, in a status it built after the cut (relayed to
        # the base station); r1 sends one as soon as its sight changes, so its date is r1's
        snap, r1_status, _ = watch.until(
            lambda s: (st := status_of(s, "r1")) and st["t_unix"] > t_cut and not st["links"]["laptop"] and st,
            SIGHT_LOST_S + 5, "r1 to lose the base station directly")
        decided, r1_lost = record["detected_unix"] - t_cut, r1_status["t_unix"] - t_cut
        print(f"\none-way {sender}->{receiver} (lease {LEASE_S:g} s): the base station counted laptop-r1 down "
              f"{decided:.3f} s after the cut (reconfigured {record['reconfigured_unix'] - t_cut:.3f} s), had lost "
              f"sight of r1 by {base_lost_by - t_cut:.3f} s; r1 lost sight of laptop by {r1_lost:.3f} s")
        assert decided <= DECIDED_S, f"the base station counted the link down {decided:.3f} s after the cut"
        assert r1_lost <= SIGHT_LOST_S, f"r1 lost the base station {r1_lost:.3f} s after the cut"
        # the base station's own sight is in its snapshots only: lost by then, maybe sooner (one poll)
        assert base_lost_by - t_cut <= SIGHT_LOST_S + POLL_S + 0.1, \
            f"the base station still saw r1 {base_lost_by - t_cut:.3f} s after the cut"

        # both views hold for the cut's duration (nothing comes back over the half that works), the
        # team goes on through a relay: r1's statuses keep arriving, its chain keeps delivering
        cut_sinks = sinks_of(snap)
        while time.time() < t_cut + CUT_S:
            s = watch.snap()
            if not s:
                continue
            r1 = status_of(s, "r1")
            # only this link: every other pair keeps its direct link
            assert not s["basestation"]["links"]["r1"] and s["links_down"] == [["laptop", "r1"]], \
                (s["basestation"]["links"], s["links_down"])
            assert not r1["links"]["laptop"], r1["links"]
            assert s["robots"]["r1"]["present"] and time.time() - r1["t_unix"] < 2 * LEASE_S + STATUS_PERIOD_S, \
                "r1's statuses stopped reaching the base station through the relay"
            time.sleep(POLL_S)
        # (c) one instance of each stage, where the placement says; every chain delivered during the cut
        held = watch.last
        check_placement(held, settled=True)
        for chain, sink in sinks_of(held).items():
            assert sink["contiguous"] > cut_sinks[chain]["contiguous"], (chain, cut_sinks[chain], sink)

        # (d) heal: every node sees every other again, the link is back in the plans after the
        # coordinator's hold, the sinks are whole
        result = run_cli(["fault", "heal", sender, receiver, "--json"], env)
        assert result.returncode == 0, result.stderr
        t_heal = json.loads(result.stdout)["fault"]["t_unix"]
        late = ZENOH_OPEN_TIMEOUT_S + 5  # the deadlines: what a reconnection may take at worst, and some
        _, _, (_, base_back) = watch.until(lambda s: s["basestation"]["links"]["r1"], late,
                                           "the base station to see r1 directly again")
        _, r1_status, _ = watch.until(
            lambda s: (st := status_of(s, "r1")) and st["t_unix"] > t_heal and st["links"]["laptop"] and st,
            late, "r1 to see the base station directly again")
        r1_back = r1_status["t_unix"] - t_heal
        _, _, (_, all_back) = watch.until(lambda s: full_sight(s, t_heal), late, "every node to see every other")
        _, _, (still_down, links_back) = watch.until(lambda s: not s["links_down"], late + LINK_BACK_AFTER_SIGHT_S,
                                                     "links_down to empty")
        sight_back = all_back - t_heal  # r1's and the base station's sight included
        print(f"heal: the base station saw r1 again by {base_back - t_heal:.3f} s, r1 saw laptop by {r1_back:.3f} s, "
              f"every node every other by {all_back - t_heal:.3f} s; links_down empty by {links_back - t_heal:.3f} s")
        # the coordinator's hold on a link back: counted from when the base station saw r1 again
        assert still_down - base_back <= LINK_BACK_AFTER_SIGHT_S, \
            f"links_down still held laptop-r1 {still_down - base_back:.3f} s after the base station saw r1 again"

        final, _, _ = watch.until(lambda s: gap_free(s) and full_sight(s, t_heal) and not s["links_down"],
                                  10, "every sink gap-free after the heal")
        check_placement(final, settled=True)
        for chain, sink in sinks_of(final).items():
            assert sink["contiguous"] > sinks_of(held)[chain]["contiguous"], (chain, sink)
        assert [f["target"] for f in final["faults"][before:]] == ["laptop-r1"], final["faults"][before:]
        watch.close()
        watch = None
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=60)
        assert proc.returncode == 0, err[-2000:]
    finally:
        if watch is not None:
            watch.close()
        stop(proc)
    # Last, so that everything else above is checked on every run: every node sees every other
    # within two leases of the heal. The base station's attempt to reconnect to r1, begun when the
    # cut closed their session, sends a SYN every second (the testbed's tcp_syn_linear_timeouts):
    # with the kernel's backoff it waited up to 3 s after the heal.
    assert sight_back <= SIGHT_BACK_S, f"every node saw every other only {sight_back:.3f} s after the heal"

