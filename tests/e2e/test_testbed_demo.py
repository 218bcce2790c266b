"""`autopower demo --testbed --json` as a user runs it: the demo story in network namespaces.

Each node in its own namespace, each link a veth pair shaped to its radio × the speed-up, every
link mutual TLS with default-deny access control, the faults cutting the real link silently.
Needs root (CI runs as root on this machine kind): without it the test fails with that reason.
Bounded: the story takes ~40 s; the demo is interrupted (it then removes its namespaces) if it
runs past its budget, and whatever is left is removed and reported by the `clean` fixture.
"""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from autopower.launch.netns import PREFIX, list_namespaces
from tests.e2e.test_testbed import clean, root  # noqa: F401 - fixtures
from tests.e2e.test_up import AUTOPOWER, env_for

pytestmark = pytest.mark.slow
BUDGET_S = 120.0  # the story runs ~40 s; a hung run must not hold CI


def run_demo(tmp_path, *args) -> subprocess.CompletedProcess:
    cmd = [AUTOPOWER, "demo", "--testbed", "--json", "--log-dir", str(tmp_path / "demo"), *args]
    proc = subprocess.Popen(cmd, env=env_for(tmp_path), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=BUDGET_S)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)  # the demo stops its team and removes its namespaces
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
        raise AssertionError(f"demo --testbed ran over {BUDGET_S:g} s; stderr ends:\n{err[-3000:]}") from None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def test_the_demo_story_in_the_testbed_with_mtls_and_access_control(tmp_path, clean):  # noqa: F811
    result = run_demo(tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout)  # one JSON object on stdout
    print(json.dumps({k: out[k] for k in ("faults", "lost_outputs", "duplicated_outputs", "migrations",
                                          "outputs", "testbed", "wall_s", "live")}, indent=1))
    # it really ran in namespaces over shaped links, every link mTLS + default-deny ACL
    assert out["security"] == "mtls+acl"
    testbed = out["testbed"]
    assert sorted(testbed["namespaces"]) == sorted(f"{PREFIX}{testbed['run']}-{n}"
                                                   for n in ("laptop", "r1", "r2", "r3", "medium1"))
    # the four radios share one 802.11a channel (a bridge), each shaped to the rate x the speed-up
    assert testbed["links"]["r1-laptop"] == {"medium": "802.11a", "kbit_s": 54000 * 5, "shared": True}
    assert testbed["shared_media"]["802.11a"]["nodes"] == ["r1", "r2", "r3", "laptop"]
    assert not set(testbed["namespaces"]) & set(list_namespaces()), "the demo left its namespaces behind"
    # the story: one silent cut (detected, replanned around through a relay), then every robot
    # cut from the base station (the robots agree on a reallocation among themselves), then a
    # SIGKILL of an agent and of the base station (each restarted in its namespace)
    assert [f["kind"] for f in out["faults"]] == ["cut", "cut", "crash-agent", "crash-basestation"]
    assert [f["parts"] for f in out["faults"]][:2] == [["r1-laptop"], ["r1-laptop", "r2-laptop", "r3-laptop"]]
    single, everyone, agent, base = out["faults"]
    assert 0 < agent["restarted_wall_s"] < agent["rejoined_wall_s"] <= 15, agent
    assert agent["battery_after_j"] < agent["battery_before_j"], agent  # its battery goes on, not reset
    assert base["reconfigured_by"].startswith("subgroup round"), base  # the robots carry on
    assert 0 < base["detected_wall_s"] <= 1.0 and 0 < base["reconfigured_wall_s"] <= 1.5, base
    assert base["taken_over_wall_s"] is not None and base["taken_over_wall_s"] <= 10, base
    assert out["supervision"]["restarts"] == {agent["target"]: 1, "laptop": 1}, out["supervision"]
    assert 0 < single["detected_wall_s"] <= 1.0, single
    assert 0 < single["reconfigured_wall_s"] <= 1.5, single
    assert single["reconfigured_by"].startswith("plan epoch")
    assert everyone["reconfigured_by"].startswith("subgroup round"), everyone
    assert 0 < everyone["detected_wall_s"] <= 1.0, everyone
    assert 0 < everyone["reconfigured_wall_s"] <= 1.5, everyone
    assert out["adopted"] >= 1  # the base station, back, started from what the subgroup ran
    # every output exactly once, counted from the recording (the replay's invariant)
    assert out["source"] == "recording"
    assert out["outputs"] > 300
    assert out["lost_outputs"] == 0 and out["duplicated_outputs"] == 0
    assert out["live"]["lost_outputs"] == 0 and out["live"]["duplicated_outputs"] == 0
    assert out["first_depletion"] is not None
    # the control plane measured on each robot's own TLS links in its namespace (the session's admin
    # space names the links under default-deny access control), charged to its radio apart
    assert out["control_j"] > 0
    for robot, counted in out["control_bytes"].items():
        assert 0 < counted["sent"] < counted["link_sent"] and 0 < counted["received"] < counted["link_received"], \
            (robot, counted)
    assert out["wall_s"] < 90


def test_demo_testbed_refuses_insecure(tmp_path, root):  # noqa: F811
    result = subprocess.run([AUTOPOWER, "demo", "--testbed", "--insecure"], env=env_for(tmp_path),
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.startswith("error: --insecure does not apply to --testbed") and result.stderr.count("\n") == 1
