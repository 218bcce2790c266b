"""`autopower up --topology relay`: r2 and r3 reach the base station only through r1's agent.

Each link is its own proxy, so the processes really cannot see each other except along the
topology's links. The mission must still start as soon as everyone is up (the base station
learns of r2 and r3 from their relayed statuses), not after the 30 s start grace.
"""

from __future__ import annotations

import json

from tests.e2e.test_up import env_for, run_cli


def test_relay_team_starts_without_waiting_for_the_grace_period(tmp_path):
    result = run_cli(["up", "paper-fig7", "--topology", "relay", "--duration", "12", "--json",
                      "--log-dir", str(tmp_path / "logs")], env_for(tmp_path), timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads(result.stdout)
    assert summary["ready"], summary
    assert summary["ready_after_s"] < 15.0, summary["ready_after_s"]  # the start grace is 30 s
    assert set(summary["placement"]) == {"Loc-1", "Loc-2", "Loc-3", "Blob-2", "Blob-3"}
    sinks = summary["basestation"]["sinks"]
    for chain in ("Blob-2", "Blob-3"):  # r2's and r3's images crossed r1 (their only link)
        assert sinks[chain]["received"] > 100 and sinks[chain]["duplicates_total"] == 0, sinks[chain]
    assert summary["robots"]["r1"]["counters"]["forwarded"] > 100
