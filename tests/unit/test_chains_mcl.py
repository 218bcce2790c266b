"""Monte-Carlo localisation and its simulated world: sizes, convergence, exact migration."""

import math
import statistics
import time

import msgpack
import numpy as np
import pytest

from autopower.chains.base import ComponentStateError, MalformedInputError
from autopower.chains.mcl import MonteCarloLocaliser, decode_estimate, score_estimate
from autopower.chains.world import (
    MAX_RANGE_M,
    LocSource,
    RobotPath,
    beam_angles_rad,
    cast_rays,
    make_building,
)

PAPER_INPUT_BYTES, PAPER_OUTPUT_BYTES = 1059, 805


# -- the world --------------------------------------------------------------------------------

def test_building_is_deterministic_walled_and_seed_dependent():
    a, b = make_building(3), make_building(3)
    assert np.array_equal(a.occupied, b.occupied)
    assert a.occupied.shape == (200, 200)
    assert a.occupied[0].all() and a.occupied[-1].all() and a.occupied[:, 0].all() and a.occupied[:, -1].all()
    assert 0.05 < a.occupied.mean() < 0.3
    assert not np.array_equal(a.occupied, make_building(4).occupied)


@pytest.mark.parametrize("robot", ["r1", "r2", "r3"])
def test_robot_tour_never_enters_a_wall_and_differs_per_robot(robot):
    building = make_building(0)
    path = RobotPath(building, robot)
    poses = path.pose_at(np.linspace(0, path.length_m, 2000))
    assert not building.is_occupied_m(poses[:, 0], poses[:, 1]).any()
    # Keep clear of walls so a robot's body would fit too.
    for dx, dy in ((0.25, 0), (-0.25, 0), (0, 0.25), (0, -0.25)):
        assert not building.is_occupied_m(poses[:, 0] + dx, poses[:, 1] + dy).any()
    assert not np.allclose(path.pose_at(0.0), RobotPath(building, "r9").pose_at(0.0))


def test_ray_casting_matches_a_fine_brute_force_march():
    building = make_building(1)
    path = RobotPath(building, "r2")
    angles = beam_angles_rad()[::7]
    for distance in (0.0, 13.0, 41.5):
        pose = path.pose_at(distance)
        fast = cast_rays(building, pose, angles)
        t = np.arange(1, 8001) * 0.001  # 1 mm steps
        world = pose[2] + angles
        xs = pose[0] + np.cos(world)[:, None] * t
        ys = pose[1] + np.sin(world)[:, None] * t
        hit = building.is_occupied_m(xs, ys)
        slow = np.where(hit.any(axis=1), t[hit.argmax(axis=1)], MAX_RANGE_M)
        assert np.abs(fast - slow).max() <= 0.0011  # the brute force's own 1 mm step


def _walk(building, pose, angle, max_range_m):
    """One beam's Amanatides & Woo walk, a cell at a time (what cast_rays must equal bit for bit)."""
    res, (rows, cols) = building.resolution_m, building.occupied.shape
    dx, dy = math.cos(pose[2] + angle), math.sin(pose[2] + angle)
    ix, iy = math.floor(pose[0] / res), math.floor(pose[1] / res)
    sx, sy = (1 if dx > 0 else -1), (1 if dy > 0 else -1)
    delta_x = res / abs(dx) if dx else math.inf
    delta_y = res / abs(dy) if dy else math.inf
    t_x = ((ix + 1) * res - pose[0] if dx > 0 else pose[0] - ix * res) / abs(dx) if dx else math.inf
    t_y = ((iy + 1) * res - pose[1] if dy > 0 else pose[1] - iy * res) / abs(dy) if dy else math.inf
    while True:
        if t_x < t_y:
            t, ix, t_x = t_x, ix + sx, t_x + delta_x
        else:
            t, iy, t_y = t_y, iy + sy, t_y + delta_y
        if t >= max_range_m:
            return max_range_m
        if not (0 <= ix < cols and 0 <= iy < rows) or building.occupied[iy, ix]:
            return t


@pytest.mark.parametrize("max_range_m", [MAX_RANGE_M, 1.5, 30.0])
def test_ray_casting_equals_the_cell_by_cell_walk_bit_for_bit(max_range_m):
    building = make_building(7)
    path = RobotPath(building, "r3")
    angles = np.concatenate([beam_angles_rad()[::5], [0.0, math.pi / 4, math.pi / 2, -3 * math.pi / 4]])
    poses = [path.pose_at(d) for d in (0.0, 7.3, 22.0, 55.5)]
    # exactly on cell corners (beams through corners: the tie rule), and outside the map
    poses += [np.array([10.0, 10.0, 0.0]), np.array([10.0, 10.0, math.pi / 4]), np.array([-1.0, 5.0, 0.3]),
              np.array([25.0, -3.0, 2.0])]
    for pose in poses:
        got = cast_rays(building, pose, angles, max_range_m)
        want = [_walk(building, pose, a, max_range_m) for a in angles]
        assert got.tolist() == want, pose


def test_source_is_deterministic_whatever_the_order_of_requests():
    in_order = LocSource("r2", seed=5)
    for seq in range(300):  # crosses an odometry chunk boundary (256 steps)
        in_order.odometry(seq)
    assert LocSource("r2", seed=5).produce(299) == in_order.produce(299)
    assert LocSource("r2", seed=5).produce(3) != in_order.produce(4)
    assert LocSource("r1", seed=5).produce(3) != in_order.produce(3)


def test_odometry_drifts_so_dead_reckoning_alone_is_not_enough():
    source = LocSource("r1", seed=0)
    start, truth = source.true_pose(0), source.true_pose(150)
    odom = source.odometry(150)
    c, s = math.cos(start[2]), math.sin(start[2])
    dead_reckoned = (start[0] + c * odom[0] - s * odom[1], start[1] + s * odom[0] + c * odom[1])
    assert math.dist(dead_reckoned, truth[:2]) > 0.5


# -- message sizes ----------------------------------------------------------------------------

@pytest.mark.parametrize("seq", [0, 1, 200, 70_000])
def test_message_sizes_are_close_to_the_papers(seq):
    source = LocSource("r2", seed=0)
    payload = source.produce(seq)
    out = MonteCarloLocaliser("r2", seed=0).run(payload)
    assert PAPER_INPUT_BYTES * 0.99 <= len(payload) <= PAPER_INPUT_BYTES, len(payload)
    assert PAPER_OUTPUT_BYTES * 0.99 <= len(out) <= PAPER_OUTPUT_BYTES, len(out)


def test_messages_never_exceed_the_papers_sizes():
    # The runtime refuses payloads above a chain's declared size (the paper's sizes), so the
    # worst case - a 4-character robot name and a 32-bit seq - must still fit.
    source = LocSource("r100", seed=0)
    payload = source.produce(0)
    obj = msgpack.unpackb(payload)
    obj["seq"] = 2**32 - 1
    worst = msgpack.packb(obj, use_bin_type=True)
    out = MonteCarloLocaliser("r100", seed=0).run(worst)
    assert len(worst) == PAPER_INPUT_BYTES and len(out) == PAPER_OUTPUT_BYTES


def test_output_carries_pose_covariance_and_top_particles():
    source = LocSource("r3", seed=2)
    estimate = decode_estimate(MonteCarloLocaliser("r3", seed=2).run(source.produce(0)))
    assert estimate.robot == "r3" and estimate.seq == 0
    assert estimate.covariance.shape == (3, 3) and np.allclose(estimate.covariance, estimate.covariance.T)
    assert (np.linalg.eigvalsh(estimate.covariance) >= 0).all()
    weights = estimate.particles[:, 3]
    assert len(weights) == 40 and (np.diff(weights) <= 0).all() and weights[0] > 0


# -- the filter -------------------------------------------------------------------------------

@pytest.mark.parametrize(("robot", "seed", "offset"), [
    ("r1", 0, (0.8, -0.6, 0.3)),
    ("r2", 1, (-1.0, 0.6, -0.4)),
    ("r3", 2, (0.5, 0.9, 0.35)),
])
def test_converges_from_an_offset_initial_belief(robot, seed, offset):
    source = LocSource(robot, seed)
    wrong_start = tuple(source.true_pose(0) + np.array(offset))
    mcl = MonteCarloLocaliser(robot, seed, initial_pose=wrong_start, initial_sigma=(1.0, 1.0, 0.5))
    prior_mean, prior_cov = mcl.estimate()
    assert math.dist(prior_mean[:2], source.true_pose(0)[:2]) > 0.5
    errors = []
    for seq in range(30):
        out = mcl.run(source.produce(seq))
        scores = score_estimate(source.ground_truth(seq), out)
        errors.append((scores["position_error_m"], scores["heading_error_rad"]))
    assert all(pos < 0.3 and head < 0.1 for pos, head in errors[10:]), errors
    final_cov = decode_estimate(out).covariance
    assert np.trace(final_cov[:2, :2]) < 0.01 * np.trace(prior_cov[:2, :2]), "the belief should tighten"


def test_tracks_a_whole_tour_while_odometry_drifts():
    source = LocSource("r1", seed=0)
    mcl = MonteCarloLocaliser("r1", seed=0)
    errors = [score_estimate(source.ground_truth(seq), mcl.run(source.produce(seq)))["position_error_m"]
              for seq in range(0, 170, 2)]  # every other message: 1.2 m per step, a full tour
    assert max(errors) < 0.3


def _run(mcl, source, seqs):
    return [mcl.run(source.produce(seq)) for seq in seqs]


@pytest.mark.parametrize("split", [0, 1, 12])
def test_migrated_filter_continues_byte_identically(split):
    source = LocSource("r2", seed=3)
    uninterrupted = MonteCarloLocaliser("r2", seed=3)
    expected = _run(uninterrupted, source, range(20))

    first = MonteCarloLocaliser("r2", seed=3)
    before = _run(first, source, range(split))
    state = first.export_state()
    migrated = MonteCarloLocaliser("r2", seed=3)
    # The fresh instance would diverge if the import did not take everything over.
    migrated.import_state(state)
    after = _run(migrated, source, range(split, 20))
    assert before + after == expected
    assert migrated.export_state() == uninterrupted.export_state()


def test_fresh_instance_without_the_state_does_not_continue_identically():
    source = LocSource("r2", seed=3)
    a = MonteCarloLocaliser("r2", seed=3)
    _run(a, source, range(12))
    b = MonteCarloLocaliser("r2", seed=3)
    assert _run(a, source, range(12, 14)) != _run(b, source, range(12, 14))


def test_state_round_trip_is_exact_and_sized_for_migration():
    source = LocSource("r1", seed=0)
    mcl = MonteCarloLocaliser("r1", seed=0)
    _run(mcl, source, range(5))
    state = mcl.export_state()
    other = MonteCarloLocaliser("r1", seed=0)
    other.import_state(state)
    assert other.export_state() == state
    assert 32_000 < len(state) < 33_000  # 1000 particles x (3 + 1) float64 + RNG and odometry


def _state_with(**changes):
    mcl = MonteCarloLocaliser("r1", seed=0)
    obj = msgpack.unpackb(mcl.export_state())
    obj.update(changes)
    return msgpack.packb(obj, use_bin_type=True)


_GOOD_STATE = MonteCarloLocaliser("r1", seed=0).export_state()
_N = 1000


@pytest.mark.parametrize(("state", "message"), [
    (b"", "not valid msgpack"),
    (b"\x00garbage", "not valid msgpack"),
    (_GOOD_STATE[:-10], "not valid msgpack"),
    (msgpack.packb([1, 2, 3]), "expected a msgpack map"),
    (msgpack.packb({"format": "x", "v": 1}), "format 'x'"),
    (_state_with(v=99), "v99"),
    (_state_with(robot="r2"), "belongs to robot 'r2'"),
    (_state_with(seed=1), "seed 1"),
    (_state_with(particles=b"\x00" * 24), "particles/weights are 24/"),
    (_state_with(particles=np.full(_N * 3, np.nan).tobytes()), "NaN"),
    (_state_with(weights=np.full(_N, 0.5).tobytes()), "sum to 1"),
    (_state_with(last_odom=[0.0, 1.0]), "last_odom"),
    (_state_with(rng={"state": b"\x00" * 3, "inc": b"\x01" * 16, "has_uint32": 0, "uinteger": 0}), "RNG"),
    (_state_with(rng={}), "RNG"),
    (_state_with(last_seq="x"), "last_seq"),
])
def test_corrupt_state_is_rejected_clearly_and_leaves_the_filter_unchanged(state, message):
    mcl = MonteCarloLocaliser("r1", seed=0)
    before = mcl.export_state()
    with pytest.raises(ComponentStateError, match=message) as excinfo:
        mcl.import_state(state)
    assert isinstance(excinfo.value, ValueError) and str(excinfo.value).startswith("Loc state: ")
    assert mcl.export_state() == before


def _input_with(**changes):
    obj = msgpack.unpackb(LocSource("r1", seed=0).produce(0))
    obj.update(changes)
    return msgpack.packb(obj, use_bin_type=True)


@pytest.mark.parametrize(("payload", "message"), [
    (b"\xc1", "not valid msgpack"),
    (LocSource("r2", seed=0).produce(0), "from robot 'r2' but this filter localises 'r1'"),
    (_input_with(front=b"\x00" * 10), "front is 10 bytes"),
    (_input_with(odom=[0.0, float("nan"), 0.0]), "odom must be 3 finite floats"),
    (_input_with(odom=[1.7e308, 0.0, 0.0]), "beyond what a robot integrates"),
    (_input_with(odom=[0.0, 0.0, -1e300]), "beyond what a robot integrates"),
    (_input_with(laser={"beams": 181, "max_mm": 8000}), "differs from the configured"),
    (_input_with(v=2), "version 2"),
    (_input_with(seq=True), "seq"),
])
def test_malformed_input_is_rejected_clearly(payload, message):
    with pytest.raises(MalformedInputError, match=message):
        MonteCarloLocaliser("r1", seed=0).run(payload)


def test_step_latency_is_well_under_50_ms():
    source = LocSource("r3", seed=0)
    mcl = MonteCarloLocaliser("r3", seed=0)
    payloads = [source.produce(seq) for seq in range(20)]
    latencies = []
    for payload in payloads:
        start = time.perf_counter()
        mcl.run(payload)
        latencies.append(time.perf_counter() - start)
    assert statistics.median(latencies) < 0.025


def test_missed_repeated_and_reordered_messages_do_not_lose_the_robot():
    # Around a migration the runtime may drop, repeat or reorder a step; the filter differences
    # integrated odometry against the last message it saw, so it still applies the right motion.
    source = LocSource("r1", seed=0)
    mcl = MonteCarloLocaliser("r1", seed=0)
    for seq in [0, 1, 2, 3, 7, 7, 6, 8, 9, 15, 16, 17]:
        scores = score_estimate(source.ground_truth(seq), mcl.run(source.produce(seq)))
        assert scores["position_error_m"] < 0.3, (seq, scores)


def _reference_weights(mcl, ranges_mm):
    """The sensor update written out beam by beam end point (cos and sin of every particle-beam
    angle, an explicit off-map mask): what `_correct`'s angle addition and border must equal."""
    from autopower.chains.mcl import _BEAM_STRIDE, _IN_WALL_LOGLIK, _RANDOM_FLOOR, _TEMPERATURE, likelihood_field
    from autopower.chains.world import MAX_RANGE_MM

    field = likelihood_field(mcl.seed)
    ranges_mm = ranges_mm[::_BEAM_STRIDE]
    valid = (ranges_mm > 0) & (ranges_mm < MAX_RANGE_MM)
    r_m = ranges_mm[valid] / 1000.0
    angles = beam_angles_rad()[::_BEAM_STRIDE][valid]
    p = mcl._particles
    res = make_building(mcl.seed).resolution_m
    loglik = np.empty((len(p), len(r_m)))
    for i, (x, y, th) in enumerate(p):
        ix = np.floor((x + r_m * np.cos(th + angles)) / res).astype(int)
        iy = np.floor((y + r_m * np.sin(th + angles)) / res).astype(int)
        inside = (ix >= 0) & (ix < field.shape[1]) & (iy >= 0) & (iy < field.shape[0])
        loglik[i] = math.log(_RANDOM_FLOOR)
        loglik[i, inside] = field[iy[inside], ix[inside]]
    in_wall = make_building(mcl.seed).is_occupied_m(p[:, 0], p[:, 1])
    logw = np.log(mcl._weights) + _TEMPERATURE * loglik.sum(axis=1) + np.where(in_wall, _IN_WALL_LOGLIK, 0.0)
    w = np.exp(logw - logw.max())
    return w / w.sum()


def test_sensor_update_equals_the_beam_by_beam_reference_also_off_the_map():
    source = LocSource("r2", seed=1)
    mcl = MonteCarloLocaliser("r2", seed=1, n_particles=300)
    _run(mcl, source, range(3))
    # Scatter a third of the particles over and beyond the whole map (each side), in walls too:
    # beams then end off the map, where only the floor may count.
    rng = np.random.default_rng(5)
    size_m = make_building(1).occupied.shape[1] * make_building(1).resolution_m
    mcl._particles[:100, :2] = rng.uniform(-0.5 * size_m, 1.5 * size_m, size=(100, 2))
    mcl._particles[:100, 2] = rng.uniform(-math.pi, math.pi, 100)
    for seq in range(3, 8):
        _, odom, ranges = mcl._parse(source.produce(seq))
        mcl._predict(odom)
        expected = _reference_weights(mcl, ranges)
        mcl._correct(ranges)
        # Rounding differs (angle addition); an end point exactly on a cell edge could fall either
        # side, so allow that for a handful of the 300 particles and no more.
        close = np.isclose(mcl._weights, expected, rtol=1e-9, atol=1e-15)
        assert close.sum() >= 297, (seq, np.flatnonzero(~close))
        mcl._last_odom = odom


def test_a_refused_reading_leaves_the_filter_as_it_was():
    # Two finite readings near the float range would overflow their difference to inf and leave
    # every particle NaN for good; the reading is refused before anything moves.
    source = LocSource("r1", seed=0)
    mcl = MonteCarloLocaliser("r1", seed=0)
    _run(mcl, source, range(3))
    before = mcl.export_state()
    for odom in ([1.7e308, 0.0, 0.0], [-1.7e308, 0.0, 0.0]):
        with pytest.raises(MalformedInputError, match="beyond what a robot integrates"):
            mcl.run(_input_with(seq=3, odom=odom))
    assert mcl.export_state() == before
    scores = score_estimate(source.ground_truth(3), mcl.run(source.produce(3)))
    assert scores["position_error_m"] < 0.3
