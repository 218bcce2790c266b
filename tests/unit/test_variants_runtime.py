"""Quality variants at run time: the real components run their variants (frame skipping, particle
count), a team runs the plan's variants and levels and its meters charge them, and the recording
scores every output against the synthetic world's ground truth."""

import zlib

import pytest

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.chains.quality import measure_variants
from autopower.chains.registry import make_component, make_source, score_output
from autopower.chains.variants import SkippingSource, measured_quality
from autopower.model.dvfs import apply_levels
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario
from autopower.model.variants import apply_variants
from autopower.recording.live import QualityScorer
from autopower.recording.recorder import Recorder
from tests.unit.sim_team import SimTeam

LOCAL = {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}


def test_frame_skipping_source_takes_every_nth_camera_frame():
    camera = make_source("Blob", "r2", 7)
    skipping = make_source("Blob", "r2", 7, {"every_nth_frame": 4})
    assert isinstance(skipping, SkippingSource)
    assert skipping.produce(3) == camera.produce(12)
    assert skipping.ground_truth(3) == camera.ground_truth(12)
    with pytest.raises(ValueError, match="every_nth_frame must be an integer"):
        make_source("Blob", "r2", 7, {"every_nth_frame": 0})


def test_localiser_runs_with_the_variants_particle_count():
    assert make_component("Loc", "r1", 7, {"n_particles": 300}).n_particles == 300
    assert make_component("Loc", "r1", 7).n_particles == 1000
    with pytest.raises(ValueError, match="does not take variant parameters n_particles"):
        make_component("Blob", "r2", 7, {"n_particles": 300})


def test_stale_blob_reports_lose_recall_over_the_skipped_frames():
    finder = make_component("Blob", "r2", 7)
    full, skip = make_source("Blob", "r2", 7), make_source("Blob", "r2", 7, {"every_nth_frame": 4})
    q_full = [measured_quality("Blob", full, k, finder.run(full.produce(k)), score_output) for k in range(8)]
    q_skip = [measured_quality("Blob", skip, k, finder.run(skip.produce(k)), score_output) for k in range(2)]
    assert sum(q["victims_total"] for q in q_full) == sum(q["victims_total"] for q in q_skip)  # same 8 frames
    assert sum(q["victims_found"] for q in q_skip) < sum(q["victims_found"] for q in q_full)


def test_declared_against_measured_quality():
    rows = {(r["component"], r["variant"]): r for r in measure_variants(load_scenario("paper-variants"), 30.0)}
    assert rows[("Blob", "4fps")]["measured"] == pytest.approx(1.0)
    assert rows[("Blob", "1fps")]["measured"] < rows[("Blob", "2fps")]["measured"] < 1.0
    assert rows[("Loc", "100p")]["outputs"] == 15 and 0 < rows[("Loc", "100p")]["measured"] <= 1


def test_a_team_runs_the_chosen_variants_at_the_planned_levels_and_meters_them():
    sc = load_scenario("paper-variants-dvfs").with_accounting("physical")
    chosen = {"Loc-1": "300p", "Blob-2": "2fps"}
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, pins=LOCAL, auto_replan=False, variants=chosen,
                                                media={"laptop-robot": "802.11a", "robot-robot": "802.11a"}),
                   fake=False)
    team.join()
    coord = team.coordinator
    assert coord.ready and coord.placing.placement == LOCAL
    assert {k: coord.variants[k] for k in chosen} == chosen
    # r1 hosts only Loc-1 at 300 particles: 0.29 / 2 = 14.5 % at 400 MHz, 58 % at 100 MHz
    assert coord.prediction.levels["r1"] == "100MHz"
    r1, r2 = team.nodes["r1"], team.nodes["r2"]
    team.run_until(10.0)
    assert r1.meter.level == "100MHz" and r1.meter.latency_factor == 4.0
    assert r1.hosted["Loc-1"].component.n_particles == 300
    assert r2.sources["Blob-2"].chain.period_s == 0.5
    assert r2.sources["Blob-2"].source.every_nth == 2
    applied = apply_levels(apply_variants(sc, coord.variants), coord.prediction.levels)
    ev = evaluate(applied, coord.deciding.plan_network, LOCAL)
    assert ev.feasible
    start = {r: team.energy(r) for r in ("r1", "r2", "r3")}
    team.run_until(70.0)
    for robot in ("r1", "r2", "r3"):
        measured_w = (team.energy(robot) - start[robot]) / 60.0
        assert measured_w == pytest.approx(ev.robots[robot].total_w, rel=2e-3), robot
        assert not team.nodes[robot].errors, team.nodes[robot].errors


class _Tel:
    rr = None

    def __init__(self):
        self.scalars = []

    def scalar(self, path, t, value):
        self.scalars.append((path, value))

    def flush(self):
        pass


def test_the_recording_scores_each_output_with_the_plans_variant():
    sc = load_scenario("paper-variants")
    tel = _Tel()
    rec = Recorder(tel, "laptop", clock=lambda: 1.0, owns_telemetry=False, quality=QualityScorer(sc))
    rec._variants = {"Blob-2": "1fps"}  # as the plan said (`_plan` keeps them)
    finder = make_component("Blob", "r2", 1234)
    seed = zlib.crc32(b"paper-variants/Blob-2")  # the agents' chain seed
    source = make_source("Blob", "r2", seed, {"every_nth_frame": 4})
    rec.on_output("Blob-2", 0, 5, finder.run(source.produce(5)))
    got = dict(tel.scalars)
    expected = measured_quality("Blob", source, 5, finder.run(source.produce(5)), score_output)
    assert got["components/Blob-2/quality/recall"] == pytest.approx(expected["recall"])
    assert got["components/Blob-2/quality/victims_total"] == expected["victims_total"]
    assert rec.errors == 0
