"""`autopower testbed up --record-dir DIR` with the testbed's one-way faults, as a user runs them.

Needs root and nftables' `nft` (CI runs as root); without them these tests fail with that
reason. Every namespace a test creates is removed, also on failure (`clean`).
"""

from __future__ import annotations

import json
import signal
import time

import pytest

from tests.e2e.test_testbed import clean, root, start_testbed, stop  # noqa: F401 - fixtures
from tests.e2e.test_up import env_for, run_cli
from tests.integration.test_testbed_loss import nft  # noqa: F401 - fixture

pytestmark = pytest.mark.slow


def test_a_recorded_testbed_run_keeps_its_loss_and_one_way_cut(tmp_path, clean, nft):  # noqa: F811
    record = tmp_path / "rec"
    proc, _session, env = start_testbed(tmp_path, "--record-dir", str(record))
    try:
        for args in (["loss", "r1", "laptop", "40", "--one-way"], ["cut", "r2", "r3", "--one-way"]):
            result = run_cli(["fault", *args], env)
            assert result.returncode == 0, result.stderr
        links = json.loads(run_cli(["fault", "list"], env).stdout)["links"]
        assert links["laptop-r1"] == "loss 40% r1->laptop" and links["r2-r3"] == "cut r2->r3", links
        for a, b in (("r1", "laptop"), ("r2", "r3")):
            assert run_cli(["fault", "heal", a, b], env).returncode == 0
        assert set(json.loads(run_cli(["fault", "list"], env).stdout)["links"].values()) == {"up"}
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=90)
        assert proc.returncode == 0, err[-2000:]
        summary = json.loads(out)
        assert summary["recording"] == str(record / "run.rrd") and summary["recording_error"] is None, summary
    finally:
        stop(proc)
    replay = run_cli(["replay", str(record / "run.rrd"), "--json"], env, timeout=120)
    assert replay.returncode == 0, replay.stderr
    faults = {(f["kind"], f["target"]): f["text"] for f in json.loads(replay.stdout)["faults"]}
    assert "40% of packets r1->laptop" in faults[("loss", "r1-laptop")], faults
    assert "r2->r3 only" in faults[("cut", "r2-r3")], faults


def test_an_unwritable_record_dir_is_refused_before_any_namespace(tmp_path, clean):  # noqa: F811
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    result = run_cli(["testbed", "up", "--record-dir", str(blocked / "rec")], env_for(tmp_path), timeout=60)
    assert result.returncode == 2
    assert result.stderr.startswith(f"error: --record-dir {blocked / 'rec'}: cannot write there"), result.stderr
    assert not list(tmp_path.rglob("testbed/*.json"))  # no run was started


def test_a_recorded_testbed_run_keeps_a_rate_change_a_flap_and_a_roam(tmp_path, clean):  # noqa: F811
    record = tmp_path / "rec"
    # GSM between the laptop and the robots: point-to-point links, whose rate can change
    proc, _session, env = start_testbed(tmp_path, "--record-dir", str(record), "--media", "laptop-robot=gsm")
    try:
        for args in (["rate", "r1", "laptop", "50"], ["flap", "r2", "r3", "--up", "0.3", "--down", "0.3", "--for", "4"],
                     ["roam", "r3", "laptop", "150"]):
            result = run_cli(["fault", *args], env)
            assert result.returncode == 0, result.stderr
        links = json.loads(run_cli(["fault", "list"], env).stdout)["links"]
        assert links["laptop-r1"] == "rate 50 kbps" and links["r2-r3"].startswith("flap 0.3s up 0.3s down"), links
        time.sleep(4.0)  # the flap's --for and the roam are over: both links up without a heal
        links = json.loads(run_cli(["fault", "list"], env).stdout)["links"]
        assert links["r2-r3"] == "up" and links["laptop-r3"] == "up", links
        assert run_cli(["fault", "heal", "r1", "laptop"], env).returncode == 0
        # a flap still running when the testbed stops is stopped with it
        assert run_cli(["fault", "flap", "r1", "r2", "--up", "60", "--down", "60"], env).returncode == 0
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=90)
        assert proc.returncode == 0, err[-2000:]
        assert json.loads(out)["recording_error"] is None
    finally:
        stop(proc)
    replay = run_cli(["replay", str(record / "run.rrd"), "--json"], env, timeout=120)
    assert replay.returncode == 0, replay.stderr
    faults = {(f["kind"], f["target"]): f["text"] for f in json.loads(replay.stdout)["faults"]}
    assert "50 kbit/s both ways" in faults[("rate", "r1-laptop")], faults
    assert "0.3 s down, 0.3 s up, for 4 s" in faults[("flap", "r2-r3")], faults
    assert "a 150 ms outage" in faults[("roam", "r3-laptop")], faults
    assert ("flap", "r1-r2") in faults, faults
