"""The live table of `up`, `testbed up` and `status`: each chain's end-to-end latency where its sink is."""

from __future__ import annotations

import io

from rich.console import Console

from autopower.cli.live_table import render
from autopower.launch.summary import chain_latencies


def sink(received: int, p50: float, worst: float, max_seq: int | None = None, duplicates: int = 0) -> dict:
    # the fields of protocol.SinkStats as a status carries them
    return {"run": 0, "received": received, "duplicates": duplicates, "contiguous": received,
            "max_seq": received - 1 if max_seq is None else max_seq, "stale": 0, "latency_ms_p50": p50,
            "latency_ms_max": worst, "received_total": received, "duplicates_total": duplicates, "digest": 0}


def snapshot() -> dict:
    robot = {"battery_j": 900.0, "initial_j": 1000.0, "power_w": {"cpu": 1.0}, "cpu_utilisation": 0.2,
             "hosted": ["Blob-2"], "sources": {}, "links": {"laptop": True}, "depleted": False}
    return {"scenario": "paper-fig7", "ready": True, "t_virtual": 10.0,
            "target": {"Blob-2": "r2"}, "placement": {"Blob-2": "r2"},
            "basestation": {"sinks": {"Blob-2": sink(120, 42.25, 180.0), "Loc-1": sink(30, 7.5, 12.0, max_seq=31)}},
            # a robot holding results for an operator it cannot reach: shown for a chain the base lacks
            "robots": {"r2": {"present": True, "status": {**robot, "sinks": {"Blob-2": sink(5, 1.0, 1.0),
                                                                            "Blob-3": sink(9, 2500.0, 4100.0)}}}}}


def test_chain_latencies_take_the_base_sink_first_and_robot_held_ones_else():
    got = chain_latencies(snapshot())
    assert list(got) == ["Blob-2", "Blob-3", "Loc-1"]
    assert got["Blob-2"] == {"sink": "base station", "outputs": 120, "p50_ms": 42.25, "max_ms": 180.0,
                             "missing": 0, "duplicated": 0}
    assert got["Blob-3"]["sink"] == "r2" and got["Blob-3"]["p50_ms"] == 2500.0
    assert got["Loc-1"]["missing"] == 2  # seqs 30 and 31 not arrived


def test_the_live_table_shows_each_chains_end_to_end_latency():
    out = io.StringIO()
    Console(file=out, width=160, color_system=None).print(render(snapshot(), 5.0))
    text = out.getvalue()
    assert "chains (end-to-end latency, source to sink)" in text
    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:-1]]
            for line in text.splitlines() if line.count("│") == 8}
    assert rows["Blob-2"] == ["base station", "120", "42.2 ms", "180 ms", "0", "0"]
    assert rows["Blob-3"] == ["r2", "9", "2,500 ms", "4,100 ms", "0", "0"]
    assert rows["Loc-1"] == ["base station", "30", "7.5 ms", "12.0 ms", "2", "0"]


def test_the_header_names_each_link_groups_medium_for_people():
    def header(media) -> str:
        out = io.StringIO()
        Console(file=out, width=200, color_system=None).print(render({**snapshot(), "media": media}, 5.0))
        return out.getvalue().splitlines()[0]

    assert "media laptop-robot=gsm, robot-robot=bluetooth" in header({"laptop-robot": "gsm",
                                                                      "robot-robot": "bluetooth"})
    assert "media —" in header(None)  # before the first plan
    assert "{" not in header({"laptop-robot": "gsm"})


def test_each_robot_shows_what_its_control_plane_draws_and_the_bytes_it_sent_and_received():
    snap = snapshot()
    status = snap["robots"]["r2"]["status"]
    status["power_w"] = {"cpu_idle": 1.0, "802.11a:control": 0.0021, "gsm:control": 0.0004, "802.11a:send": 0.5}
    status["control_bytes"] = [74_448, 52_345]
    out = io.StringIO()
    Console(file=out, width=200, color_system=None).print(render(snap, 5.0))
    row = next(line for line in out.getvalue().splitlines() if line.startswith("│ r2 "))
    assert [c.strip() for c in row.split("│")[1:-1]][3] == "0.0025 (74/52)"


def test_each_robot_shows_what_its_runtimes_own_cpu_draws_and_the_cpu_seconds_it_took():
    snap = snapshot()
    status = snap["robots"]["r2"]["status"]
    status["power_w"] = {"cpu_idle": 1.0, "cpu_runtime": 0.0412, "802.11a:send": 0.5}
    status["runtime_cpu_s"] = 3.26
    out = io.StringIO()
    Console(file=out, width=220, color_system=None).print(render(snap, 5.0))
    row = next(line for line in out.getvalue().splitlines() if line.startswith("│ r2 "))
    assert [c.strip() for c in row.split("│")[1:-1]][4] == "0.041 (3.3)"
