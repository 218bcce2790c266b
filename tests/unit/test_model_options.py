"""Model options real teams need, each off by default (the paper's Fig. 7 stays exact), and the
rules a user relies on: the routing tie-break, the lifetime rounding, infeasibility reported
with its cause, reference rows on explicit topologies."""

from __future__ import annotations

import pytest

from autopower.errors import InfeasibleError
from autopower.model.energy import evaluate, round_lifetime
from autopower.model.loading import load_scenario
from autopower.model.network import build_network
from autopower.planner import PlanRequest, plan
from autopower.planner.analysis import analyze

# Robots listed in an order their names do not sort in: cam, zed, amy (names sort amy < cam < zed).
TINY = """
[scenario]
name = "tiny"
accounting = "paper"
lifetime_rounding_s = 0.8

[platforms.sitsang]
idle_w = 1.34
busy_w = 2.27
[platforms.laptop]
mains = true

[radios."802.11a"]
kbps = 54000
sleep_w = 0.010
send_w = 1.498
receive_w = 1.2
[radios.bluetooth]
kbps = 1500
sleep_w = 0.000036
send_w = 0.095
receive_w = 0.095

[basestation]
name = "laptop"
platform = "laptop"
{base_extra}

[[robots]]
name = "cam"
platform = "sitsang"
energy_j = 64000
sensors = ["camera"]
[[robots]]
name = "zed"
platform = "sitsang"
energy_j = 64000
sensors = ["camera"]
[[robots]]
name = "amy"
platform = "sitsang"
energy_j = 64000
sensors = ["camera"]

[network]
topology = "explicit"
# listed so that link order and name order both favour amy
[[network.links]]
a = "amy"
b = "laptop"
media = {up_media}
group = "uplink"
[[network.links]]
a = "cam"
b = "amy"
media = ["802.11a"]
[[network.links]]
a = "zed"
b = "laptop"
media = {up_media}
group = "uplink"
[[network.links]]
a = "cam"
b = "zed"
media = ["802.11a"]

[components.Blob]
latency_s = {{ sitsang = 0.115, laptop = 0.01048 }}

[[chains]]
name = "Blob-cam"
source = "cam"
sink = "operator"
component = "Blob"
period_s = 1.0
message_bytes = [76800, 200]   # 0.4 s of Bluetooth airtime per image
{pin}
[[chains]]
name = "Blob-zed"
source = "zed"
sink = "operator"
component = "Blob"
period_s = 1.0
message_bytes = [76800, 200]
{pin}
[[chains]]
name = "Blob-amy"
source = "amy"
sink = "operator"
component = "Blob"
period_s = 1.0
message_bytes = [76800, 200]
{pin}
{rows}
"""


def tiny(tmp_path, *, base_extra="", up_media='["bluetooth"]', pin='pin = "laptop"', rows=""):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY.format(base_extra=base_extra, up_media=up_media, pin=pin, rows=rows))
    return load_scenario(path)


def test_equal_hop_routes_follow_node_order_not_names(tmp_path):
    s = tiny(tmp_path)
    network = build_network(s)
    # cam reaches the laptop in two hops through zed or through amy: zed is listed first
    assert [hop[:2] for hop in network.route("cam", "laptop")] == [("cam", "zed"), ("zed", "laptop")]
    # the same network with the robots listed the other way round routes through amy
    flipped = tmp_path / "flipped"
    flipped.mkdir()
    text = TINY.format(base_extra="", up_media='["bluetooth"]', pin="", rows="")
    zed = '[[robots]]\nname = "zed"\nplatform = "sitsang"\nenergy_j = 64000\nsensors = ["camera"]\n'
    amy = zed.replace("zed", "amy")
    text = text.replace(zed, "@@").replace(amy, zed).replace("@@", amy)
    (flipped / "tiny.toml").write_text(text)
    assert [hop[:2] for hop in build_network(load_scenario(flipped / "tiny.toml")).route("cam", "laptop")] == \
        [("cam", "amy"), ("amy", "laptop")]


def test_lifetime_rounding_is_nearest_with_halves_up():
    assert round_lifetime(2.0, 0.8) == 2.4  # 2.5 quanta: up (Python's round would give 1.6)
    assert round_lifetime(1.2, 0.8) == 1.6  # 1.5 quanta: up
    assert round_lifetime(1.19, 0.8) == 0.8
    assert round_lifetime(45715.21, 0.8) == 45715.2
    assert round_lifetime(123.456, 0) == 123.456  # 0 = no rounding


def test_basestation_radios_unlimited_by_default_limited_on_request(tmp_path):
    free = tiny(tmp_path)
    everything_on_laptop = {"Blob-cam": "laptop", "Blob-zed": "laptop", "Blob-amy": "laptop"}
    ev = evaluate(free, build_network(free), everything_on_laptop)
    # zed and amy send 0.4 s/s each straight up, cam's images come through zed: 1.2 s/s at the laptop
    assert ev.basestation_radio_busy["bluetooth"] == pytest.approx(1.2, rel=1e-3)
    assert ev.feasible  # the paper's model: the base station's radios are not limited

    (tmp_path / "limited").mkdir()
    limited = tiny(tmp_path / "limited", base_extra="limit_radios = true")
    ev = evaluate(limited, build_network(limited), everything_on_laptop)
    assert not ev.feasible
    [violation] = ev.violations
    assert (violation.node, violation.resource) == ("laptop", "radio:bluetooth")
    assert violation.value == pytest.approx(1.2, rel=1e-3)
    assert "by 20.0 points" in violation.message


def test_planners_respect_the_basestation_radio_limit(tmp_path):
    limited = tiny(tmp_path, base_extra="limit_radios = true", pin="")
    by_method = {}
    for method in ("exhaustive", "milp"):
        p = plan(PlanRequest(scenario=limited, method=method))
        assert p.evaluation.feasible
        assert p.evaluation.basestation_radio_busy.get("bluetooth", 0.0) <= 1.0 + 1e-9
        by_method[method] = p.evaluation.lifetime_s
    assert by_method["milp"] == pytest.approx(by_method["exhaustive"], rel=1e-6)


def test_infeasible_pinned_plan_names_the_resource_and_the_media_tried(tmp_path):
    limited = tiny(tmp_path, base_extra="limit_radios = true")
    with pytest.raises(InfeasibleError) as err:
        plan(PlanRequest(scenario=limited))
    text = str(err.value)
    assert "with the media fixed (uplink=bluetooth" in text
    assert "laptop radio:bluetooth utilisation 120.0% exceeds 100%" in text
    assert "any media choice" not in text


def test_analyze_reports_an_infeasible_media_pair_as_infeasible_never_optimal(tmp_path):
    s = tiny(tmp_path, base_extra="limit_radios = true", up_media='["bluetooth", "802.11a"]')
    rows, _ = analyze(s)
    by_uplink = {}
    for row in rows:
        if row.label in ("optimal", "infeasible"):
            by_uplink[row.media["uplink"]] = row
    assert by_uplink["bluetooth"].label == "infeasible"
    assert by_uplink["bluetooth"].evaluation is None and by_uplink["bluetooth"].allocation == {}
    assert "laptop radio:bluetooth" in by_uplink["bluetooth"].reason
    d = by_uplink["bluetooth"].to_dict(None)
    assert d["feasible"] is False and d["lifetime_s"] is None and d["reason"]
    assert by_uplink["802.11a"].label == "optimal" and by_uplink["802.11a"].evaluation.feasible


def test_reference_rows_on_an_explicit_topology(tmp_path):
    rows_toml = """
[[reference_rows]]
topology = "explicit"
media = { uplink = "802.11a" }
allocation = { Blob-cam = "cam", Blob-zed = "laptop", Blob-amy = "amy" }
paper_lifetime_s = 1.0
"""
    s = tiny(tmp_path, up_media='["bluetooth", "802.11a"]', pin="", rows=rows_toml)
    [ref] = s.reference_rows
    assert ref.media_by_group()["uplink"] == "802.11a"
    rows, _ = analyze(s)
    [row] = [r for r in rows if r.label == "paper-row-1"]
    assert row.allocation["Blob-zed"] == "laptop"
    assert row.evaluation.network.medium_between("zed", "laptop") == "802.11a"
    assert row.evaluation.feasible
