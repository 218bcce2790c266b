"""Monte-Carlo localisation of one robot in the building of ``autopower.chains.world``.

A particle filter in the style of CARMEN's localiser (Thrun, Burgard & Fox, Probabilistic
Robotics, ch. 5-6 and 8):

* motion model: the odometry motion model (rotate, translate, rotate) with noise growing with
  the motion; the motion is the difference between this message's integrated odometry and the
  last one the filter saw, so a missed or repeated message costs accuracy, not correctness;
* sensor model: a likelihood field (Gaussian in the distance from a beam's end point to the
  nearest wall, plus a floor for unexplained readings) over every 8th of the 480 beams,
  tempered so 60 correlated beams do not count as 60 independent ones;
* low-variance resampling when the effective sample size drops below half the particles.

The filter starts from a Gaussian around its robot's start pose (the robot knows where it was
put down, roughly). Its state - particles, weights, the last odometry and the RNG - round-trips
exactly through ``export_state``/``import_state``: a filter migrated mid-run produces the same
bytes as one that was not.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autopower.chains.base import (
    ComponentStateError,
    MalformedInputError,
    check_seed,
    pack,
    require_fields,
    robot_key,
    unpack_map,
)
from autopower.chains.world import (
    BEAMS_PER_SCANNER,
    INPUT_VERSION,
    MAX_RANGE_MM,
    Building,
    RobotPath,
    beam_angles_rad,
    make_building,
    wrap_rad,
)

OUTPUT_VERSION = 1
STATE_FORMAT = "autopower.chains.mcl"
STATE_VERSION = 1
N_REPORTED_PARTICLES = 40  # top-weighted particles in the output: 799-805 bytes in all
# Odometry no robot's mission reaches (1,000 km, and a heading of 10^6 rad if it is not wrapped):
# a reading beyond it is refused, as a NaN would be.
MAX_ODOM_M = 1e6
MAX_ODOM_RAD = 1e6

# Motion noise (Probabilistic Robotics' alpha1..alpha4), a little wider than the simulated
# odometry's, plus a floor so particles keep some diversity when the robot stands still.
_ALPHA_ROT_ROT, _ALPHA_ROT_TRANS, _ALPHA_TRANS_TRANS, _ALPHA_TRANS_ROT = 0.08, 0.02, 0.08, 0.02
_MIN_SIGMA_M, _MIN_SIGMA_RAD = 0.01, 0.005
_INITIAL_SIGMA = (0.3, 0.3, 0.15)  # m, m, rad around the known start pose

# Likelihood field.
_HIT_SIGMA_M = 0.1
_RANDOM_FLOOR = 0.02  # relative likelihood of a reading the map does not explain
_FIELD_MAX_M = 0.6  # distances beyond this all get the floor anyway (exp(-18) ~ 0)
_BEAM_STRIDE = 8
_TEMPERATURE = 0.25  # log-likelihood multiplier: beams are far from independent
_IN_WALL_LOGLIK = -50.0  # a particle inside a wall is impossible whatever the laser says


@dataclass(frozen=True)
class LocEstimate:
    """A decoded localisation output message."""

    robot: str
    seq: int
    pose: tuple[float, float, float]  # x_m, y_m, theta_rad in the map frame
    covariance: np.ndarray  # 3x3, (m, m, rad)
    n_eff: float
    particles: np.ndarray  # (K, 4) float32: x_m, y_m, theta_rad, weight; heaviest first


@functools.lru_cache(maxsize=16)
def likelihood_field(seed: int) -> np.ndarray:
    """Log-likelihood of a beam ending in each cell of building ``seed`` (float64, rows = y).

    Distance to the nearest occupied cell is found exactly up to ``_FIELD_MAX_M`` by taking the
    minimum over all cell offsets within that radius (no scipy needed; ~20 ms, cached).
    """
    building = make_building(seed)
    occupied, res = building.occupied, building.resolution_m
    reach = int(math.ceil(_FIELD_MAX_M / res))
    rows, cols = occupied.shape
    padded = np.zeros((rows + 2 * reach, cols + 2 * reach), dtype=bool)
    padded[reach:reach + rows, reach:reach + cols] = occupied
    dist2 = np.full(occupied.shape, np.inf)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            d2 = float(dx * dx + dy * dy) * res * res
            if d2 > _FIELD_MAX_M ** 2:
                continue
            shifted = padded[reach + dy:reach + dy + rows, reach + dx:reach + dx + cols]
            np.minimum(dist2, np.where(shifted, d2, np.inf), out=dist2)
    prob = np.exp(-dist2 / (2 * _HIT_SIGMA_M ** 2)) + _RANDOM_FLOOR
    field = np.log(prob)
    field.setflags(write=False)
    return field


@functools.lru_cache(maxsize=16)
def bordered_likelihood_field(seed: int) -> np.ndarray:
    """``likelihood_field(seed)`` inside a one-cell border of the floor (a beam ending off the map
    explains nothing): clipping a cell index to this array is the whole bounds check."""
    field = likelihood_field(seed)
    bordered = np.full((field.shape[0] + 2, field.shape[1] + 2), math.log(_RANDOM_FLOOR))
    bordered[1:-1, 1:-1] = field
    bordered.setflags(write=False)
    return bordered


class MonteCarloLocaliser:
    """The "Loc" component for one robot: ``run(odometry + scans) -> pose estimate``."""

    component_type = "Loc"

    def __init__(self, robot: str, seed: int, n_particles: int = 1000,
                 initial_pose: tuple[float, float, float] | None = None,
                 initial_sigma: tuple[float, float, float] = _INITIAL_SIGMA) -> None:
        """Filter for ``robot`` in building ``seed``.

        The initial belief is a Gaussian (``initial_sigma``: m, m, rad) around ``initial_pose``,
        by default the robot's true start pose (it knows roughly where it was put down).
        """
        if not 10 <= n_particles <= 100_000:
            raise ValueError(f"n_particles must be 10..100000, got {n_particles}")
        self.robot = robot
        self.seed = check_seed(seed)
        self.n_particles = n_particles
        self._building: Building = make_building(seed)
        self._bordered_field = bordered_likelihood_field(seed)
        angles = beam_angles_rad()
        self._beam_index = np.arange(0, angles.size, _BEAM_STRIDE)
        self._beam_angles = angles[self._beam_index]
        if initial_pose is None:
            start = RobotPath(self._building, robot).pose_at(0.0)
        else:
            start = np.array(initial_pose, dtype=np.float64)
        self._rng = np.random.Generator(np.random.PCG64([seed, robot_key(robot), 0x3C1]))
        self._particles = start + self._rng.normal(size=(n_particles, 3)) * np.array(initial_sigma)
        self._particles[:, 2] = wrap_rad(self._particles[:, 2])
        self._weights = np.full(n_particles, 1.0 / n_particles)
        self._last_odom = np.zeros(3)  # the odometry frame's origin is the start pose
        self._last_seq = -1

    # -- the component interface -------------------------------------------------------------

    def run(self, payload: bytes) -> bytes:
        """One filter step: motion update, sensor update, estimate, resample if needed."""
        seq, odom, ranges_mm = self._parse(payload)
        self._predict(odom)
        self._correct(ranges_mm)
        output = self._encode_estimate(seq)
        n_eff = 1.0 / float(np.sum(self._weights ** 2))
        if n_eff < self.n_particles / 2:
            self._resample()
        self._last_odom = odom
        self._last_seq = seq
        return output

    def export_state(self) -> bytes:
        """Particles, weights, last odometry and RNG state as msgpack (exact float64 bytes)."""
        rng_state = self._rng.bit_generator.state
        return pack({
            "format": STATE_FORMAT, "v": STATE_VERSION, "robot": self.robot, "seed": self.seed,
            "n": self.n_particles,
            "particles": self._particles.astype("<f8").tobytes(),
            "weights": self._weights.astype("<f8").tobytes(),
            "last_odom": [float(v) for v in self._last_odom],
            "last_seq": self._last_seq,
            "rng": {
                # PCG64's 128-bit integers do not fit msgpack ints: send them as 16 bytes.
                "state": rng_state["state"]["state"].to_bytes(16, "little"),
                "inc": rng_state["state"]["inc"].to_bytes(16, "little"),
                "has_uint32": rng_state["has_uint32"], "uinteger": rng_state["uinteger"],
            },
        })

    def import_state(self, state: bytes) -> None:
        """Adopt a state from ``export_state`` of a filter for the same robot, seed and size.

        Raises ``ComponentStateError`` (a ``ValueError``) saying what is wrong; on error this
        instance is left unchanged.
        """
        what = "Loc state"
        obj = unpack_map(state, what, ComponentStateError)
        require_fields(obj, {"format": str, "v": int}, what, ComponentStateError)
        if obj["format"] != STATE_FORMAT or obj["v"] != STATE_VERSION:
            raise ComponentStateError(
                f"{what}: format {obj['format']!r} v{obj['v']}, expected {STATE_FORMAT!r} v{STATE_VERSION}")
        require_fields(obj, {"robot": str, "seed": int, "n": int, "particles": bytes, "weights": bytes,
                             "last_odom": list, "last_seq": int, "rng": dict}, what, ComponentStateError)
        if (obj["robot"], obj["seed"], obj["n"]) != (self.robot, self.seed, self.n_particles):
            raise ComponentStateError(
                f"{what}: belongs to robot {obj['robot']!r}, seed {obj['seed']}, {obj['n']} particles; this "
                f"filter is robot {self.robot!r}, seed {self.seed}, {self.n_particles} particles")
        n = self.n_particles
        if len(obj["particles"]) != n * 3 * 8 or len(obj["weights"]) != n * 8:
            raise ComponentStateError(
                f"{what}: particles/weights are {len(obj['particles'])}/{len(obj['weights'])} bytes, "
                f"expected {n * 24}/{n * 8} for {n} particles")
        particles = np.frombuffer(obj["particles"], dtype="<f8").reshape(n, 3).astype(np.float64)
        weights = np.frombuffer(obj["weights"], dtype="<f8").astype(np.float64)
        if not (np.isfinite(particles).all() and np.isfinite(weights).all()):
            raise ComponentStateError(f"{what}: particles or weights contain NaN/inf")
        if (weights < 0).any() or not math.isclose(float(weights.sum()), 1.0, rel_tol=1e-6):
            raise ComponentStateError(f"{what}: weights must be >= 0 and sum to 1 (sum {weights.sum()!r})")
        odom = obj["last_odom"]
        if len(odom) != 3 or not all(_is_finite_number(v) for v in odom):
            raise ComponentStateError(f"{what}: last_odom must be 3 finite floats, got {odom!r}")
        rng = np.random.Generator(np.random.PCG64())
        try:
            r = obj["rng"]
            rng.bit_generator.state = {
                "bit_generator": "PCG64",
                "state": {"state": int.from_bytes(r["state"], "little"), "inc": int.from_bytes(r["inc"], "little")},
                "has_uint32": int(r["has_uint32"]), "uinteger": int(r["uinteger"]),
            }
            if len(r["state"]) != 16 or len(r["inc"]) != 16:
                raise ValueError("state and inc must be 16 bytes each")
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise ComponentStateError(f"{what}: bad RNG state ({exc!r})") from exc
        self._particles, self._weights, self._rng = particles, weights, rng
        self._last_odom = np.array(odom, dtype=np.float64)
        self._last_seq = obj["last_seq"]

    # -- the filter ----------------------------------------------------------------------------

    def _parse(self, payload: bytes) -> tuple[int, np.ndarray, np.ndarray]:
        what = "Loc input"
        msg = unpack_map(payload, what)
        require_fields(msg, {"v": int, "robot": str, "seq": int, "odom": list, "laser": dict,
                             "front": bytes, "rear": bytes}, what)
        if msg["v"] != INPUT_VERSION:
            raise MalformedInputError(f"{what}: version {msg['v']}, expected {INPUT_VERSION}")
        if msg["robot"] != self.robot:
            raise MalformedInputError(
                f"{what}: message is from robot {msg['robot']!r} but this filter localises {self.robot!r}")
        odom = msg["odom"]
        if len(odom) != 3 or not all(_is_finite_number(v) for v in odom):
            raise MalformedInputError(f"{what}: odom must be 3 finite floats [x_m, y_m, theta_rad], got {odom!r}")
        # Finite is not enough: the motion is a difference of two odometry readings, and two near
        # the float range overflow to inf, which would leave every particle NaN for good.
        if max(abs(odom[0]), abs(odom[1])) > MAX_ODOM_M or abs(odom[2]) > MAX_ODOM_RAD:
            raise MalformedInputError(
                f"{what}: odom {odom!r} is beyond what a robot integrates (|x|, |y| <= {MAX_ODOM_M:g} m, "
                f"|theta| <= {MAX_ODOM_RAD:g} rad); the message was not applied")
        laser = msg["laser"]
        if laser.get("beams") != BEAMS_PER_SCANNER or laser.get("max_mm") != MAX_RANGE_MM:
            raise MalformedInputError(
                f"{what}: laser {laser!r} differs from the configured {BEAMS_PER_SCANNER} beams, {MAX_RANGE_MM} mm")
        for key in ("front", "rear"):
            if len(msg[key]) != 2 * BEAMS_PER_SCANNER:
                raise MalformedInputError(
                    f"{what}: {key} is {len(msg[key])} bytes, expected {2 * BEAMS_PER_SCANNER} (uint16 per beam)")
        ranges = np.frombuffer(msg["front"] + msg["rear"], dtype="<u2")
        return msg["seq"], np.array(odom, dtype=np.float64), ranges

    def _predict(self, odom: np.ndarray) -> None:
        """Odometry motion model: sample rot1, trans, rot2 for every particle."""
        last = self._last_odom
        c, s = math.cos(last[2]), math.sin(last[2])
        gx, gy = odom[0] - last[0], odom[1] - last[1]
        dx, dy = c * gx + s * gy, -s * gx + c * gy  # motion in the last odometry pose's frame
        trans = math.hypot(dx, dy)
        # Below 1 cm the direction of travel is noise: treat the motion as a pure rotation.
        rot1 = math.atan2(dy, dx) if trans > 0.01 else 0.0
        rot2 = float(wrap_rad(odom[2] - last[2] - rot1))
        n = self.n_particles
        noise = self._rng.normal(size=(n, 3))
        sd_rot1 = _ALPHA_ROT_ROT * abs(rot1) + _ALPHA_ROT_TRANS * trans + _MIN_SIGMA_RAD
        sd_trans = _ALPHA_TRANS_TRANS * trans + _ALPHA_TRANS_ROT * (abs(rot1) + abs(rot2)) + _MIN_SIGMA_M
        sd_rot2 = _ALPHA_ROT_ROT * abs(rot2) + _ALPHA_ROT_TRANS * trans + _MIN_SIGMA_RAD
        r1 = rot1 + noise[:, 0] * sd_rot1
        tr = trans + noise[:, 1] * sd_trans
        r2 = rot2 + noise[:, 2] * sd_rot2
        p = self._particles
        heading = p[:, 2] + r1
        p[:, 0] += tr * np.cos(heading)
        p[:, 1] += tr * np.sin(heading)
        p[:, 2] = wrap_rad(heading + r2)

    def _correct(self, ranges_mm: np.ndarray) -> None:
        """Weight particles by the likelihood field at their beams' end points.

        Particles x beams is 60,000 end points a step, the filter's whole cost: each is found by
        angle addition (a cosine and a sine per particle and per beam, not per pair) in cells of
        a field with a one-cell border of the floor, so an end point off the map needs no mask.
        """
        ranges_mm = ranges_mm[self._beam_index]
        valid = (ranges_mm > 0) & (ranges_mm < MAX_RANGE_MM)  # max range = no return: no evidence
        if not valid.any():
            return
        cells_per_m = 1.0 / self._building.resolution_m
        r_cells = ranges_mm[valid].astype(np.float64) * (cells_per_m / 1000.0)
        angles = self._beam_angles[valid]
        beam_x, beam_y = r_cells * np.cos(angles), r_cells * np.sin(angles)
        p = self._particles
        cos_th, sin_th = np.cos(p[:, 2:3]), np.sin(p[:, 2:3])
        # +1: the border. Column/row of the end point in the bordered field, cell by cell.
        end_x = cos_th * beam_x
        end_x -= sin_th * beam_y
        end_x += p[:, 0:1] * cells_per_m + 1.0
        end_y = sin_th * beam_x
        end_y += cos_th * beam_y
        end_y += p[:, 1:2] * cells_per_m + 1.0
        field = self._bordered_field
        rows, cols = field.shape
        # Clipped to the border first, then truncated: for values >= 0 that is the floor, and
        # anything below 0 (off the map) lands on the border either way.
        np.clip(end_x, 0, cols - 1, out=end_x)
        np.clip(end_y, 0, rows - 1, out=end_y)
        cell = end_y.astype(np.intp)
        cell *= cols
        cell += end_x.astype(np.intp)
        loglik = field.ravel().take(cell)
        in_wall = self._building.is_occupied_m(p[:, 0], p[:, 1])
        score = _TEMPERATURE * loglik.sum(axis=1) + np.where(in_wall, _IN_WALL_LOGLIK, 0.0)
        with np.errstate(divide="ignore"):
            logw = np.log(self._weights) + score
        logw -= logw.max()
        w = np.exp(logw)
        self._weights = w / w.sum()

    def _resample(self) -> None:
        """Low-variance (systematic) resampling: one random number, N evenly spaced pointers."""
        n = self.n_particles
        pointers = (self._rng.random() + np.arange(n)) / n
        cumulative = np.cumsum(self._weights)
        index = np.minimum(np.searchsorted(cumulative, pointers, side="right"), n - 1)
        self._particles = self._particles[index]
        self._weights = np.full(n, 1.0 / n)

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Weighted mean pose (circular mean heading) and its 3x3 covariance."""
        w, p = self._weights, self._particles
        heading = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
        mean = np.array([float(w @ p[:, 0]), float(w @ p[:, 1]), heading])
        d = p - mean
        d[:, 2] = wrap_rad(d[:, 2])
        cov = (d * w[:, None]).T @ d
        return mean, cov

    def _encode_estimate(self, seq: int) -> bytes:
        """The output message: 796 bytes + len(robot) + 1-5 bytes for seq (799-801 for "r1").

        Never more than the paper's 805 for robot names of up to 4 characters (the runtime
        refuses outputs larger than the chain's declared size).
        """
        mean, cov = self.estimate()
        top = np.argsort(-self._weights, kind="stable")[:N_REPORTED_PARTICLES]
        particles = np.column_stack([self._particles[top], self._weights[top]]).astype("<f4")
        return pack({
            "v": OUTPUT_VERSION, "robot": self.robot, "seq": seq,
            "pose": [float(v) for v in mean],  # x_m, y_m, theta_rad in the map frame
            "cov": [float(v) for v in cov.ravel()],  # row-major 3x3
            "n_eff": 1.0 / float(np.sum(self._weights ** 2)),
            "top": particles.tobytes(),  # K x (x_m, y_m, theta_rad, weight), little-endian float32
        })


def _is_finite_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def decode_estimate(data: bytes) -> LocEstimate:
    """Decode a localisation output message (raises ``MalformedInputError`` if it is not one)."""
    what = "Loc output"
    obj = unpack_map(data, what)
    require_fields(obj, {"v": int, "robot": str, "seq": int, "pose": list, "cov": list,
                         "n_eff": float, "top": bytes}, what)
    if obj["v"] != OUTPUT_VERSION or len(obj["pose"]) != 3 or len(obj["cov"]) != 9 or len(obj["top"]) % 16:
        raise MalformedInputError(f"{what}: bad layout (v={obj['v']}, {len(obj['pose'])} pose values, "
                                  f"{len(obj['cov'])} cov values, {len(obj['top'])} particle bytes)")
    return LocEstimate(
        robot=obj["robot"], seq=obj["seq"], pose=tuple(float(v) for v in obj["pose"]),  # type: ignore[arg-type]
        covariance=np.array(obj["cov"], dtype=np.float64).reshape(3, 3), n_eff=obj["n_eff"],
        particles=np.frombuffer(obj["top"], dtype="<f4").reshape(-1, 4),
    )


def score_estimate(truth: dict[str, Any], output: bytes) -> dict[str, float]:
    """Compare a localisation output with ``LocSource.ground_truth``: position and heading error."""
    est = decode_estimate(output)
    x, y, th = est.pose
    return {
        "position_error_m": math.hypot(x - truth["x_m"], y - truth["y_m"]),
        "heading_error_rad": abs(float(wrap_rad(th - truth["theta_rad"]))),
    }
