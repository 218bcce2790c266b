"""Random faults through the command line against a team under `up`, then the replay's verdict.

`bench/bench_random_faults.py` starts the paper's mission under `autopower up` (three agents, the
base station, every link through its proxy, a recording), injects faults drawn from a seed with
`autopower fault ...` (cuts of any link, every robot cut from the base station, heals, SIGKILLs of
any node, freezes, radio changes), heals everything, lets the team run 15 s more, stops `up` and
replays the recording with `autopower replay --json`. This runs a short one (12 faults, seed 6:
every robot cut from the base station three times, r1 and the base station SIGKILLed, the base
station twice, a freeze, a heal, a radio change) as a subprocess, in its own session so that a
timeout kills `up` and its children too, once as `up` sets the stage workers by default (off on a
machine of fewer than four cores) and once with every stage in a worker process. Bounded: 12
faults, one team, 420 s each.

What a user relies on: every command is taken or refused with its reason, `up` stops cleanly, no output reaches its sink
twice, no process raises, the metered energy agrees with the model, no result is dropped (a robot
cut off from its sink keeps its results within its hold budget until the sink is back), and what is
missing at the sinks is what the design lets go (outputs of a robot's chains that died in its
memory at a SIGKILL), counted apart by the replay.
Nothing is lost, and nothing is *abandoned* (docs/known-limits.md: the inputs an old run still had
waiting upstream when its chain started a new run): a chain stopped by a fault goes on in its run
when its source robot's process holds the run's position; a new run starts when the operator or a
failed component stopped it, or its source robot restarted without its saved position (killed before
its first resume snapshot), and none of these faults has done that in the runs measured.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_random_faults.py"
SEED, FAULTS = 6, 12
TIMEOUT_S = 420.0


@pytest.mark.parametrize("stage_workers", ["auto", "on"])
def test_a_team_under_random_faults_repeats_nothing_and_its_energy_agrees_with_the_model(stage_workers, tmp_path):
    """``on``: every stage's component in a worker process of its own (issue 30 item 4): a released
    or killed worker stage loses and repeats nothing the in-process one would not."""
    env = {**os.environ, "TMPDIR": str(tmp_path), "RERUN_ANALYTICS": "0"}
    proc = subprocess.Popen([sys.executable, str(BENCH), "--seed", str(SEED), "--faults", str(FAULTS), "--json",
                             "--stage-workers", stage_workers],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the bench, `up` and every process of the team
        proc.communicate()
        raise AssertionError(f"the random-fault run took over {TIMEOUT_S:g} s (files in {tmp_path})") from None
    assert proc.returncode == 0, err[-3000:]
    result = json.loads(out)  # --json: one object on stdout, nothing else
    where = f"(logs and recording in {result['workdir']})"

    assert len(result["faults"]) >= FAULTS
    # taken, or refused with exit 2 and the reason (a command the base station cannot apply while it
    # listens to its robots after a restart, say): never a crash, never a silent failure
    assert all(f["exit"] == 0 or (f["exit"] == 2 and f["refusal"].startswith("error:")) for f in result["faults"]), \
        [f for f in result["faults"] if f["exit"]]
    assert sum(f["exit"] == 0 for f in result["faults"]) >= FAULTS - 2
    assert result["up_exit"] == 0, where
    assert not [m for m in result["log_errors"] if "Traceback" in m or "Error:" in m], result["log_errors"]

    assert result["duplicated"] == 0, where
    outputs = result["outputs_recorded"]
    assert outputs > 500, where  # the chains ran (and the sinks recorded) across the faults
    # cut off from the base station three times: every result kept until the sink was back
    assert result["dropped_by_budget"] == 0, where
    assert result["lost"] == 0, (result["lost"], outputs, where)
    # an old run's tail is abandoned only when its chain starts a new run (docs/known-limits.md): 0 here
    # with and without stage workers, 0 of 5,550 in seed 8's 20 faults (435 of 5,317 there when every
    # fault-stopped chain started a new run)
    assert result["abandoned"] == 0, (result["abandoned"], outputs, where)
    failed = [i["name"] for i in result["failed_invariants"] if i["name"] != "every output exactly once at its sink"]
    assert not failed, (result["failed_invariants"], where)

    assert abs(result["energy_model_error_pct"]) <= 3.0, (result["energy_model_error_pct"], where)
    for robot, error in result["energy_error_pct_per_robot"].items():
        assert error is not None and abs(error) <= 10.0, (robot, error, where)
