"""CI's sweep of the simulated team (`autopower sim`): a fixed set of seeds, each drawing its own
faults, each judged by the oracle. Every seed must pass: one that fails is a finding (shrink it with
``autopower sim --seed N ... --shrink``, find the cause, pin a runtime bug in
tests/unit/test_teamsim_findings.py).

The kinds whose runtime bugs are still open are left out here, and so are the seeds that found one
still open (they are pinned there); put them back once the finding is fixed.
"""

from __future__ import annotations

import os

import pytest

from autopower.teamsim import KINDS
from autopower.teamsim.sweep import Sweep, sweep

OPEN_FINDINGS: tuple[str, ...] = ()  # fault kinds whose runtime bug is still open (pinned in test_teamsim_findings.py)
PLAN = Sweep(mission_s=30.0, n_faults=4, quiet_s=20.0, kinds=tuple(k for k in KINDS if k not in OPEN_FINDINGS))
# Seeds that found a runtime bug, with the plan they found it under (a seed's faults depend on the
# kinds drawn from): each one is a regression test in test_teamsim_findings.py. The kinds are
# spelled out: a kind added later must not change the faults these seeds draw.
KINDS_BEFORE_RADIO = ("cut", "cut-one-way", "partition", "loss", "duplicate", "reorder", "crash", "freeze",
                      "basestation-crash", "migrate", "toggle")
FOUND_PLAN = Sweep(mission_s=30.0, n_faults=4, quiet_s=20.0,
                   kinds=tuple(k for k in KINDS_BEFORE_RADIO if k not in ("loss", "duplicate")))
FOUND = (90, 118)
# seeds that fail since the simulated robots run subgroup rounds (strict xfail, pinned in
# test_teamsim_findings.py until fixed), under the plan they were found with
ROUNDS_PLAN = Sweep(mission_s=30.0, n_faults=4, quiet_s=20.0, kinds=KINDS_BEFORE_RADIO)
# 46 (outputs lost around a base station frozen past the lease, with cuts and frozen robots) passes
# this plan since statuses go as their change from a whole one (fewer bytes on the links, other
# timings): not a fix, the finding is open without a seed that shows it. Seeds 0-210 of this plan
# all pass (2026-11-30).
FOUND_WITH_ROUNDS: tuple[int, ...] = ()
# seeds of this sweep that failed since it draws the radio impairments too: a link slowed below the
# chain's data rate, and custody's resends queued behind their originals. Fixed (frames past the
# consumer's highest seq wait while it keeps rising: `node.custody`); 16 and 110 run in the sweep
# again, the unit test in test_custody.py pins the rule
FOUND_WITH_RADIO: tuple[int, ...] = ()
# seeds that fail since the silence detector learns each link's loss (it no longer takes a peer behind
# a lossy or fast-flapping link for gone). 46 (a gate that gives a gap up while its producer is still
# resending) passes this plan since acknowledgements left the statuses: the lossy link draws its
# losses over other messages. Not a fix: test_custody pins the gate, and 46 still fails the rounds plan.
FOUND_WITH_ACCRUAL: tuple[int, ...] = ()
# seeds that failed because a gate's report freed the inputs waiting behind a gap from their
# producer's custody: a stage restarted without state after its migration was given up saw inputs
# no one had run (`custody.is_run`). Fixed; 479 (beyond this range) and 187 (the rounds plan) are
# regression tests in test_teamsim_findings.py, the others run in the sweep again.
# seeds beyond this range that failed (a 500-seed run of this plan): 354, a migration to r1 over a
# lossy link that a base station's crash left starting for good; fixed (an adopted stage still
# waiting for its state is a migration of the adopter's), a regression test in
# test_teamsim_findings.py. (168, in this range, lost a result its host lost on the link and
# crashed before resending: fixed, a regression test there.)
# (372 lost two results of a chain's older run, made obsolete by its sink's newer run; it passes
# since statuses split, by timing: test_custody pins the mechanism.)
FIXED_BEYOND_RANGE = (354,)
# seeds beyond this range that fail (a 2,000-seed run of this plan, 611-2610, 2026-11-30: 12 of them;
# 211-610 all pass). Each failed the same way on the code before that session's fixes: open findings,
# strict xfails in test_teamsim_findings.py. Outputs lost around radio rate drops (1008, 1065, 1411,
# 1550, 2524: a link slowed below the chain's rate, as 16 and 110), one-way cuts with crashes or
# freezes (634, 1626, 1647, 1664, 1989, 2106) and a flapping link with a partition (2171). Since
# statuses go on the heartbeat (fewer bytes on the slowed link, other timings), 2037 of the first
# class passes and 2524 of it fails (every frame resent behind its original on the slowed link):
# 12 of 2,400 seeds (211-2610) before and after.
# The slowed-link fix (custody, 2026-11-30) fixed 1008, 1411, 2524 and 1647, 1664, 1989 (each also has a
# link slowed below a chain's rate, with its crashes or freezes), and 1550 once the simulated link
# sent its backlog at the rate restored (it held it to the slow rate): regression tests in
# test_teamsim_findings.py. A 2,611-seed run (0-2610) after both fails these five and no other.
FIXED_SLOWED_LINKS_BEYOND_RANGE = (1008, 1411, 1550, 1647, 1664, 1989, 2524)
# The last five of that run, fixed (2026-11-30): a gate gave a gap up after 10 s while a flapping link
# ate its producer's resends (1626, 2171: a gate now waits while its producer's floor says it holds the
# gap); a released stage ran the inputs waiting behind a gap its producer, in sight, still held (2106:
# they are left to it); a robot killed with camera frames or results in its hands only (634, 1065: the
# restarted robot names them, and the oracle takes the label only for what a kill took,
# `teamsim.evidence`). Regression tests in test_teamsim_findings.py. A 4,611-seed run (0-4610) after
# these fails only 4024 (below).
FIXED_GAPS_AND_KILLS_BEYOND_RANGE = (634, 1065, 1626, 2106, 2171)
# seeds beyond this range that fail (the 4,611-seed run, 2026-11-30): none since 4024 was fixed
# (below).
FOUND_BEYOND_RANGE: tuple[int, ...] = ()
# 4024 (fixed 2026-11-30): a stage moved from the laptop to r2 0.1 s before the base station's kill:
# its last two outputs were delivered to the laptop's sink but not yet committed, the laptop's own
# acknowledgement (every 0.1 s, before the commit) had let its custody drop them, the move said their
# inputs were run, and r2 dropped the inputs. A node now acknowledges to itself only what its sinks
# committed (`NodeRuntime.commit_sinks`), and a moving stage takes the outputs only the old host's
# memory holds with its state (`StateTransfer.outputs`). A regression test in test_teamsim_findings.py.
FIXED_UNCOMMITTED_OUTPUTS = (4024,)
# 1695 (beyond this range, fixed 2026-11-30): r3 was killed with camera frames for the laptop's Blob-3
# in its custody only (a partition had eaten them), and the base station never saw it go (the keyframe
# of r1's status saying it had lost r3 was lost on a lossy link, and its deltas could not be applied
# for 10 s), so Blob-3 kept running on the laptop, its gate waiting for the first of them. The
# restarted r3 went on past them with its floor there; the gate ran the next frame past the gap and
# the stage, whose state expected the gap, failed. An instance with state now starts afresh at a floor
# that would skip an input (`Hosting.start_afresh`): the unit test in test_custody.py pins the rule,
# the seed is a regression test in test_teamsim_findings.py.
FIXED_RESTARTED_PRODUCER_BEYOND_RANGE = (1695,)
# seeds whose sink counted a copy a duplicating link made on an earlier hop of a routed packet (the
# oracle took the copy for one the team made): 53 and 270 (in this range), 382 (a regression test)
FIXED_FORWARDED_COPIES = (53, 270, 382)
FIXED_WAITING_INPUTS = (25, 31, 62, 63, 100, 119, 182, 479)
FIXED_WAITING_INPUTS_WITH_ROUNDS = (187,)
# seeds that failed since a peer's statuses may stay away for the lease and a period before it counts
# as silent (`runtime.cadence.silence_limit_s`): the robots took a frozen base station for gone half
# a second later, and that timing met a sink's newer run making the results of its older run that
# custody still held obsolete. Fixed (a sink reports the older runs it remembers, `Ack.older`); 91
# runs in the sweep again, 372 (beyond this range) is a regression test.
FIXED_OLD_RUNS = (91, 372)
SEEDS = [seed for seed in range(211) if seed not in FOUND_WITH_RADIO + FOUND_WITH_ACCRUAL]


CHUNKS = 4  # the sweep in parts, so that `./run tests` spreads it over its workers


@pytest.mark.slow
@pytest.mark.parallel
@pytest.mark.parametrize("chunk", range(CHUNKS), ids=lambda c: f"part{c + 1}of{CHUNKS}")
def test_every_seed_of_the_sweep_passes(chunk):
    seeds = SEEDS[chunk::CHUNKS]
    # one process per pytest worker under xdist (the workers fill the cores), both cores alone
    jobs = 1 if os.environ.get("PYTEST_XDIST_WORKER") else min(2, os.cpu_count() or 1)
    verdicts = sweep(PLAN, seeds, jobs=jobs)
    failed = [f"seed {v.seed}: {v.first} ({PLAN.command(v.seed)})" for v in verdicts if not v.ok]
    assert not failed, f"{len(failed)} of {len(seeds)} seeds failed:\n" + "\n".join(failed)


# The DAG scenario (a fan-in chain fed by three others' stages): its seeds with a base-station crash
# found that a takeover restarted the fan-in chain in a run its sink had (fixed; the regression test
# is in tests/unit/test_teamsim.py). 16 lost outputs around a radio rate drop until the slowed-link
# fix (FOUND_WITH_RADIO).
DAG_PLAN = Sweep(scenario="paper-teammap", mission_s=30.0, n_faults=4, quiet_s=20.0, kinds=PLAN.kinds)
DAG_SEEDS = list(range(1, 41))


@pytest.mark.slow
@pytest.mark.parallel
def test_every_seed_of_the_dag_sweep_passes():
    """(40 seeds: 15 s on two cores.)"""
    jobs = 1 if os.environ.get("PYTEST_XDIST_WORKER") else min(2, os.cpu_count() or 1)
    verdicts = sweep(DAG_PLAN, DAG_SEEDS, jobs=jobs)
    failed = [f"seed {v.seed}: {v.first} ({DAG_PLAN.command(v.seed)})" for v in verdicts if not v.ok]
    assert not failed, f"{len(failed)} of {len(DAG_SEEDS)} seeds failed:\n" + "\n".join(failed)
