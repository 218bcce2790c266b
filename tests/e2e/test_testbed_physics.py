"""With links shaped like their radios, an allocation the model calls infeasible really falls behind.

paper-fig7 with GSM between the laptop and the robots: the model says running both Blob finders
on the laptop needs each robot's GSM radio busy 1564 % of the time (every 230 KB camera frame
crosses it), while the optimum (Blob finders on their robots) keeps the radio nearly idle. On
loopback both run alike; in the testbed the infeasible one misses periods and its frames arrive
seconds late, while the optimum keeps up. One run each, same machine, same speed.
"""

from __future__ import annotations

import math
import os
import time

import pytest

from autopower.cli.options import build_scenario
from autopower.launch.localhost import TeamSpec
from autopower.launch.netns import list_namespaces
from autopower.launch.testbed import TestbedTeam
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from tests.integration.runtime_helpers import sinks_of, sources_of

pytestmark = pytest.mark.slow
MEDIA = ("laptop-robot=gsm",)
INFEASIBLE = ("Blob-2=laptop", "Blob-3=laptop")
RUN_S = 15.0


def blob_figures(pins, tmp_path) -> tuple[dict, list[str]]:
    spec = TeamSpec(scenario="paper-fig7", speed=5.0, media=MEDIA, pins=pins, lease_ms=3000,
                    log_dir=tmp_path / ("infeasible" if pins else "optimal"))
    with TestbedTeam(spec, build_scenario("paper-fig7")) as team:
        namespaces = team.net.namespaces
        team.wait_ready(120)
        time.sleep(RUN_S)
        # statuses cross the same saturated radio as the frames: judge on ones from late in the
        # run, not on one that left a robot before its camera had started (0 produced, 0 missed)
        deadline = time.monotonic() + 30.0
        while True:
            snap = team.snapshot()
            times = {r: (v.get("status") or {}).get("t_virtual") or 0.0 for r, v in snap["robots"].items()}
            if min(times.values()) >= 0.5 * RUN_S * spec.speed:
                break
            # the control plane rides ahead of the frames (`carries_chain_data`): a status waits
            # for the batch on air and the socket's buffer, seconds on GSM, never the whole run
            assert time.monotonic() < deadline, (
                f"pins {pins}: after {RUN_S:g} s and 30 s more the base station's latest statuses are from "
                f"virtual {times} (base at {snap.get('t_virtual')}): the robots' statuses do not cross the radio")
            time.sleep(0.5)
    sources, sinks = sources_of(snap), sinks_of(snap)
    out = {}
    scenario = build_scenario("paper-fig7")
    for chain in ("Blob-2", "Blob-3"):
        produced, missed = sources[chain]["produced_total"], sources[chain]["missed"]
        source_t = (snap["robots"][scenario.chain(chain).source].get("status") or {}).get("t_virtual") or 0.0
        out[chain] = {"placement": snap["placement"][chain], "produced": produced,
                      # frames per virtual second of the run: the two runs last different times, and a
                      # source whose chain was paused (its consumer out of reach) counts no period at all
                      "rate": produced / max(source_t, 1e-9),
                      # outputs at the sink per virtual second: what crossed the radio
                      "delivered": (sinks[chain]["received_total"] if chain in sinks else 0) / max(source_t, 1e-9),
                      "missed_ratio": missed / max(1, produced + missed),
                      # no output through at all (the laptop's one GSM radio receives for every
                      # robot): its latency is unbounded
                      "latency_ms_p50": sinks[chain]["latency_ms_p50"] if chain in sinks else math.inf}
    return out, namespaces


def test_an_infeasible_allocation_falls_behind_while_the_optimum_keeps_up(tmp_path):
    if os.geteuid() != 0:
        pytest.fail("the testbed needs root (network namespaces); CI runs it as root")
    scenario = load_scenario("paper-fig7")
    network = build_network(scenario, media={"laptop-robot": "gsm"})
    laptop_all = {s: "laptop" for s in ("Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3")}
    assert not evaluate(scenario, network, laptop_all).feasible, "the model must call it infeasible"
    optimal, made = blob_figures((), tmp_path)
    infeasible, made_too = blob_figures(INFEASIBLE, tmp_path)
    print("optimal", optimal, "\ninfeasible", infeasible)
    assert not set(made + made_too) & set(list_namespaces()), "a team left its namespaces behind"
    for chain in ("Blob-2", "Blob-3"):
        good, bad = optimal[chain], infeasible[chain]
        assert good["placement"] != "laptop" and bad["placement"] == "laptop"
        assert good["latency_ms_p50"] < 500 and good["missed_ratio"] < 0.15, good
        assert bad["latency_ms_p50"] > 1000, bad  # frames wait behind the radio
        # it misses periods, and gets far fewer outputs through per virtual second (a rate: the runs
        # last different times, the wait above for a late status is longer behind a saturated
        # radio). The model: the laptop's GSM radio would have to be busy 1564 % of the time, so at
        # most ~1/16 of the frames cross it; asserted with room: under a quarter of the optimum's.
        # (Until 2026-11-24 this compared the frames *produced*, < half the optimum's: that
        # measured how soon custody's buffers filled and paused the source, not the radio; with
        # no frame resent only for waiting in a queue, the source paused less: 51 % of the
        # optimum's in one CI run.)
        assert bad["missed_ratio"] > 0.2 and bad["delivered"] < good["delivered"] / 4, (bad, good)
