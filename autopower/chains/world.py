"""The building the robots search, and a simulated robot driving through it.

* ``make_building(seed)``: a 20 m x 20 m floor as a 200 x 200 occupancy grid (0.1 m cells):
  outer walls, a cross of 2 m corridors, eight rooms with one door each onto the east-west
  corridor and furniture along their back walls. Door positions and furniture depend on the
  seed, which also breaks the floor's symmetry so a laser can tell the rooms apart.
* ``RobotPath``: a closed tour along the corridor and into every room and back; each robot
  starts at its own point of the tour (and half of them drive it backwards).
* ``LocSource``: the "Loc" chain's source: per step ``seq``, the robot's odometry and the two
  laser scans it would see, as one msgpack message of about 1059 bytes (the paper's
  localisation input size, which it never exceeds).

Laser: a front and a rear scanner at the robot centre, 180 deg each, 240 beams each (0.75 deg
apart), 8 m range, ranges in mm as little-endian uint16 (8000 = no return). Odometry is the
robot's pose in its odometry frame (origin = where it started), integrated from per-step motion
with noise, so it drifts like a real wheel encoder. Sending the integrated pose (as CARMEN
does) rather than a per-step delta means a filter that misses or repeats a message, e.g.
around a migration, still applies the right motion: it differences against the last odometry
it saw.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autopower.chains.base import check_seed, check_seq, pack, robot_key

RESOLUTION_M = 0.1
SIZE_CELLS = 200
SIZE_M = SIZE_CELLS * RESOLUTION_M  # 20 m
CORRIDOR_Y_M = (9.0, 11.0)  # the east-west corridor every door opens onto
CORRIDOR_X_M = (9.0, 11.0)  # the north-south corridor
WALL_M = 0.2

BEAMS_PER_SCANNER = 240
SCANNER_FOV_RAD = math.pi
SCANNER_MOUNTS_RAD = (0.0, math.pi)  # front, rear (both at the robot centre)
MAX_RANGE_M = 8.0
MAX_RANGE_MM = int(round(MAX_RANGE_M * 1000))
RANGE_NOISE_M = 0.01
CLUTTER_PROB = 0.005  # a beam blocked by something not on the map (a person, a door leaf)

STEP_M = 0.6  # robot travel per localisation step: 0.3 m/s at one step per 2 s
INPUT_VERSION = 1


def beam_angles_rad() -> np.ndarray:
    """Angles of all 480 beams in the robot frame, front scanner's 240 first."""
    k = np.arange(BEAMS_PER_SCANNER)
    rel = -SCANNER_FOV_RAD / 2 + (k + 0.5) * (SCANNER_FOV_RAD / BEAMS_PER_SCANNER)
    return np.concatenate([mount + rel for mount in SCANNER_MOUNTS_RAD])


def wrap_rad(angle: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle) + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class Room:
    """A room: its free interior (m), door centre x on the corridor wall, and side (+1 north, -1 south)."""

    x0_m: float
    x1_m: float
    y0_m: float
    y1_m: float
    door_x_m: float
    side: int


@dataclass(frozen=True)
class Building:
    """An occupancy grid (``occupied[row=y, col=x]``) and the rooms it was built from."""

    occupied: np.ndarray
    rooms: tuple[Room, ...]
    resolution_m: float = RESOLUTION_M

    def is_occupied_m(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Occupancy at world points (m); points outside the map count as occupied."""
        ix = np.floor(np.asarray(x_m) / self.resolution_m).astype(np.int64)
        iy = np.floor(np.asarray(y_m) / self.resolution_m).astype(np.int64)
        rows, cols = self.occupied.shape
        inside = (ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)
        out = np.ones(np.shape(ix), dtype=bool)
        out[inside] = self.occupied[iy[inside], ix[inside]]
        return out


@functools.lru_cache(maxsize=16)
def make_building(seed: int) -> Building:
    """The seeded building floor (cached: it is immutable and shared by sources and filters)."""
    check_seed(seed)
    rng = np.random.default_rng([seed, 0xB1D6])
    grid = np.zeros((SIZE_CELLS, SIZE_CELLS), dtype=bool)
    centres = (np.arange(SIZE_CELLS) + 0.5) * RESOLUTION_M

    def fill(x0: float, y0: float, x1: float, y1: float, value: bool = True) -> None:
        cols = (centres >= x0) & (centres < x1)
        rows = (centres >= y0) & (centres < y1)
        grid[np.ix_(rows, cols)] = value

    w = WALL_M
    outer_walls = ((0, 0, SIZE_M, w), (0, SIZE_M - w, SIZE_M, SIZE_M), (0, 0, w, SIZE_M), (SIZE_M - w, 0, SIZE_M, SIZE_M))
    for wall in outer_walls:
        fill(*wall)
    (cy0, cy1), (cx0, cx1) = CORRIDOR_Y_M, CORRIDOR_X_M
    rooms: list[Room] = []
    for side, (ry0, ry1) in ((-1, (w, cy0 - w)), (+1, (cy1 + w, SIZE_M - w))):
        corridor_wall = (cy0 - w, cy0) if side < 0 else (cy1, cy1 + w)
        fill(0, corridor_wall[0], cx0, corridor_wall[1])
        fill(cx1, corridor_wall[0], SIZE_M, corridor_wall[1])
        fill(cx0 - w, ry0, cx0, ry1)  # the north-south corridor's walls
        fill(cx1, ry0, cx1 + w, ry1)
        for qx0, qx1 in ((w, cx0 - w), (cx1 + w, SIZE_M - w)):
            mid = round((qx0 + qx1) / 2 + float(rng.uniform(-0.8, 0.8)), 1)  # room split varies
            fill(mid - w / 2, ry0, mid + w / 2, ry1)
            for x0, x1 in ((qx0, mid - w / 2), (mid + w / 2, qx1)):
                door_x = round(float(rng.uniform(x0 + 0.9, x1 - 0.9)), 1)
                fill(door_x - 0.5, corridor_wall[0], door_x + 0.5, corridor_wall[1], False)
                rooms.append(Room(x0, x1, ry0, ry1, door_x, side))
    for room in rooms:
        # Furniture only in the far part of the room: the robot's tour goes 3 m in and back.
        far0, far1 = (room.y0_m, room.y0_m + 3.5) if room.side < 0 else (room.y1_m - 3.5, room.y1_m)
        for _ in range(int(rng.integers(2, 4))):
            bw, bh = (float(v) for v in rng.uniform(0.4, 1.3, size=2))
            bx = float(rng.uniform(room.x0_m, room.x1_m - bw))
            by = float(rng.uniform(far0, far1 - bh))
            fill(bx, by, bx + bw, by + bh)
    grid.setflags(write=False)
    return Building(occupied=grid, rooms=tuple(rooms))


class RobotPath:
    """A robot's closed tour through the building, as pose = f(distance travelled)."""

    ROOM_DEPTH_M = 3.0  # how far past the door the robot drives into each room

    def __init__(self, building: Building, robot: str) -> None:
        key = robot_key(robot)
        south = sorted((r for r in building.rooms if r.side < 0), key=lambda r: r.door_x_m)
        north = sorted((r for r in building.rooms if r.side > 0), key=lambda r: -r.door_x_m)
        corridor_y = sum(CORRIDOR_Y_M) / 2
        points: list[tuple[float, float]] = []
        for room in south + north:
            door_y = CORRIDOR_Y_M[0] if room.side < 0 else CORRIDOR_Y_M[1]
            points += [(room.door_x_m, corridor_y),
                       (room.door_x_m, door_y + room.side * self.ROOM_DEPTH_M),
                       (room.door_x_m, corridor_y)]
        if key & 1:  # half of the robots drive the tour the other way round
            points.reverse()
        points.append(points[0])
        self.points = np.array(points)
        seg = np.diff(self.points, axis=0)
        self._seg_len = np.hypot(seg[:, 0], seg[:, 1])
        self._seg_heading = np.arctan2(seg[:, 1], seg[:, 0])
        self._cum = np.concatenate([[0.0], np.cumsum(self._seg_len)])
        self.length_m = float(self._cum[-1])
        self.start_m = (key % 1000) / 1000 * self.length_m

    def pose_at(self, distance_m: np.ndarray | float) -> np.ndarray:
        """Pose(s) ``[x_m, y_m, theta_rad]`` after driving ``distance_m`` from the robot's start."""
        s = (self.start_m + np.atleast_1d(np.asarray(distance_m, dtype=np.float64))) % self.length_m
        seg = np.clip(np.searchsorted(self._cum, s, side="right") - 1, 0, len(self._seg_len) - 1)
        along = s - self._cum[seg]
        heading = self._seg_heading[seg]
        x = self.points[seg, 0] + along * np.cos(heading)
        y = self.points[seg, 1] + along * np.sin(heading)
        poses = np.stack([x, y, heading], axis=-1)
        return poses[0] if np.ndim(distance_m) == 0 else poses


def cast_rays(building: Building, pose: np.ndarray, angles_rad: np.ndarray,
              max_range_m: float = MAX_RANGE_M) -> np.ndarray:
    """Exact range (m) from ``pose`` along each beam to the first occupied cell, or max range.

    Grid traversal (Amanatides & Woo) without the walk: a beam's first hit is the nearest of its
    cell-boundary crossings that enters an occupied cell, so every crossing of every beam is
    computed at once (whole arrays, no loop over steps). The crossing distances are the walk's
    own running sums and its tie rule is kept (at a cell corner the row changes first), so the
    ranges are the walk's, bit for bit. The beams that hit nothing near are done again further.
    """
    res = building.resolution_m
    world = pose[2] + np.asarray(angles_rad, dtype=np.float64)
    dx, dy = np.cos(world), np.sin(world)
    ix = int(math.floor(pose[0] / res))
    iy = int(math.floor(pose[1] / res))
    with np.errstate(divide="ignore", invalid="ignore"):
        delta_x = np.where(dx != 0, res / np.abs(dx), np.inf)
        delta_y = np.where(dy != 0, res / np.abs(dy), np.inf)
        first_x = np.where(dx > 0, (ix + 1) * res - pose[0], pose[0] - ix * res)
        first_y = np.where(dy > 0, (iy + 1) * res - pose[1], pose[1] - iy * res)
        t_x = np.where(dx != 0, first_x / np.abs(dx), np.inf)
        t_y = np.where(dy != 0, first_y / np.abs(dy), np.inf)
    beams = _Beams(t_x, t_y, delta_x, delta_y, np.where(dx > 0, 1, -1), np.where(dy > 0, 1, -1))
    full = int(math.ceil(max_range_m / res)) + 2  # crossings of one kind a beam makes within range, + 1
    near = min(full, _NEAR_CROSSINGS)
    rows, cols = building.occupied.shape
    pad = full + max(0, -ix, ix - cols + 1, -iy, iy - rows + 1)  # no crossing within range leaves it
    ranges, settled = _first_hits(building, ix, iy, beams, near, max_range_m, pad)
    if near < full and not settled.all():
        far = ~settled
        ranges[far], _ = _first_hits(building, ix, iy, beams.subset(far), full, max_range_m, pad)
    return ranges


_NEAR_CROSSINGS = 32  # crossings of each kind looked at first (about 3 m): most beams hit a wall by then


@dataclass(frozen=True)
class _Beams:
    t_x: np.ndarray  # distance to the first vertical (horizontal) cell boundary
    t_y: np.ndarray
    delta_x: np.ndarray  # distance between two vertical (horizontal) cell boundaries
    delta_y: np.ndarray
    step_x: np.ndarray  # +1 / -1: the column (row) a crossing moves to
    step_y: np.ndarray

    def subset(self, mask: np.ndarray) -> "_Beams":
        return _Beams(*(getattr(self, f)[mask] for f in ("t_x", "t_y", "delta_x", "delta_y", "step_x", "step_y")))


def _first_hits(building: Building, ix: int, iy: int, beams: _Beams, n: int, max_range_m: float,
                pad: int) -> tuple[np.ndarray, np.ndarray]:
    """Each beam's range over its first ``n`` crossings of each kind, and whether that is final.

    A hit is final when no crossing left out comes before it (the last computed crossing of
    each kind is not nearer); a beam with neither a hit nor crossings left within range is done.
    """
    xs = _crossings(beams.t_x, beams.delta_x, n)
    ys = _crossings(beams.t_y, beams.delta_y, n)
    flat, width = _padded_grid(building, pad + 1)
    origin = (iy + pad + 1) * width + (ix + pad + 1)
    k = np.arange(1, n + 1)
    row_step = (beams.step_y * width)[:, None]
    col_step = beams.step_x[:, None]
    # an x crossing moves one column, into the row reached by every y crossing not after it
    # (at a corner the y crossing goes first), and the other way round
    x_cells = origin + k * col_step + _crossed(ys, xs, beams.t_y, beams.delta_y, True) * row_step
    y_cells = origin + k * row_step + _crossed(xs, ys, beams.t_x, beams.delta_x, False) * col_step
    ranges = np.full(xs.shape[0], max_range_m)
    for t, cells in ((xs, x_cells), (ys, y_cells)):
        hit = flat[cells] & (t < max_range_m)
        ranges = np.minimum(ranges, np.where(hit, t, max_range_m).min(axis=1))
    horizon = np.minimum(xs[:, -1], ys[:, -1])
    return ranges, (ranges <= horizon) | (horizon >= max_range_m)


def _crossings(first: np.ndarray, delta: np.ndarray, n: int) -> np.ndarray:
    """The first ``n`` crossing distances of each beam, summed one step at a time as the walk does."""
    steps = np.empty((first.size, n))
    steps[:, 0] = first
    steps[:, 1:] = delta[:, None]
    return np.cumsum(steps, axis=1)


def _crossed(seq: np.ndarray, at: np.ndarray, first: np.ndarray, delta: np.ndarray, inclusive: bool) -> np.ndarray:
    """How many of each beam's crossings ``seq`` come before each of its distances ``at``.

    Counted from the arithmetic (a float division), which is exact unless ``at`` is within a
    hair of a crossing; those few are counted against the running sums themselves.
    ``inclusive``: a crossing at the same distance counts.
    """
    n = seq.shape[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        g = (at - first[:, None]) / delta[:, None]
    finite = np.isfinite(g)
    g = np.where(finite, g, -1.0)  # inf: no such crossing within range (counted 0; never a hit)
    count = np.minimum(np.maximum(np.floor(g) + 1, 0), n).astype(np.int64)
    rows, cols = np.nonzero(finite & (np.abs(g - np.round(g)) < 1e-6))
    if rows.size:
        c, v = count[rows, cols], at[rows, cols]
        for _ in range(3):
            above = seq[rows, np.minimum(c, n - 1)]
            below = seq[rows, np.maximum(c - 1, 0)]
            c = (c + ((c < n) & ((above <= v) if inclusive else (above < v)))
                 - ((c > 0) & ((below > v) if inclusive else (below >= v))))
        count[rows, cols] = c
    return count


_PADDED: dict[tuple[int, int], tuple[Building, np.ndarray, int]] = {}


def _padded_grid(building: Building, pad: int) -> tuple[np.ndarray, int]:
    """The occupancy grid inside a border of occupied cells ``pad`` wide, flat, and its width.

    Outside the map counts as occupied, and no index of a beam within range leaves the border.
    """
    key = (id(building), pad)
    got = _PADDED.get(key)
    if got is None or got[0] is not building:
        if len(_PADDED) >= 64:
            _PADDED.clear()
        rows, cols = building.occupied.shape
        grid = np.ones((rows + 2 * pad, cols + 2 * pad), dtype=bool)
        grid[pad:pad + rows, pad:pad + cols] = building.occupied
        got = _PADDED[key] = (building, grid.ravel(), cols + 2 * pad)  # holds the building: its id stays its
    return got[1], got[2]


class LocSource:
    """The "Loc" chain's source on one robot: odometry + laser scans for step ``seq``.

    Deterministic in (robot, seed, seq) whatever order steps are asked for; odometry is cached
    because each step's odometry integrates all the motion before it.
    """

    component_type = "Loc"
    _CHUNK = 256  # odometry noise is drawn (and integrated) in chunks of this many steps

    def __init__(self, robot: str, seed: int) -> None:
        self.robot = robot
        self.seed = check_seed(seed)
        self._key = robot_key(robot)
        self.building = make_building(seed)
        self.path = RobotPath(self.building, robot)
        self._angles = beam_angles_rad()
        self._odom = np.zeros((1, 3))  # odometry pose at seq 0, 1, ...: starts at the origin

    def true_pose(self, seq: int) -> np.ndarray:
        """Ground-truth pose ``[x_m, y_m, theta_rad]`` at step ``seq``."""
        return self.path.pose_at(check_seq(seq) * STEP_M)

    def odometry(self, seq: int) -> np.ndarray:
        """Noisy integrated odometry pose at step ``seq`` in the odometry frame (origin = start)."""
        check_seq(seq)
        while len(self._odom) <= seq:
            self._extend_odometry()
        return self._odom[seq].copy()

    def _extend_odometry(self) -> None:
        first = len(self._odom)  # steps first .. first + CHUNK - 1
        chunk = (first - 1) // self._CHUNK  # first is always 1 + a multiple of CHUNK
        steps = np.arange(first - 1, first + self._CHUNK)
        poses = self.path.pose_at(steps * STEP_M)
        prev, cur = poses[:-1], poses[1:]
        # True motion of each step in the frame of the pose before it.
        c, s = np.cos(prev[:, 2]), np.sin(prev[:, 2])
        gx, gy = cur[:, 0] - prev[:, 0], cur[:, 1] - prev[:, 1]
        dx, dy = c * gx + s * gy, -s * gx + c * gy
        dth = wrap_rad(cur[:, 2] - prev[:, 2])
        trans = np.hypot(dx, dy)
        rng = np.random.default_rng([self.seed, self._key, 0x0D0, chunk])
        n = self._CHUNK
        dx = dx + rng.normal(0, 1, n) * (0.03 * trans + 0.005)
        dy = dy + rng.normal(0, 1, n) * (0.01 * trans + 0.002)
        dth = dth + rng.normal(0, 1, n) * (0.03 * np.abs(dth) + 0.01 * trans + 0.002)
        # Integrate in the (drifting) odometry frame.
        x0, y0, th0 = self._odom[-1]
        th = th0 + np.cumsum(dth)
        th_before = np.concatenate([[th0], th[:-1]])
        x = x0 + np.cumsum(np.cos(th_before) * dx - np.sin(th_before) * dy)
        y = y0 + np.cumsum(np.sin(th_before) * dx + np.cos(th_before) * dy)
        block = np.stack([x, y, wrap_rad(th)], axis=-1)
        self._odom = np.concatenate([self._odom, block])

    def scan_mm(self, seq: int) -> np.ndarray:
        """The 480 laser ranges (uint16 mm; front scanner first) seen at step ``seq``."""
        pose = self.true_pose(seq)
        ranges = cast_rays(self.building, pose, self._angles)
        rng = np.random.default_rng([self.seed, self._key, 0x1A5E, seq])
        ranges = ranges + rng.normal(0, RANGE_NOISE_M, ranges.shape)
        clutter = rng.random(ranges.shape) < CLUTTER_PROB
        ranges = np.where(clutter, rng.uniform(0.1, 1.0, ranges.shape) * ranges, ranges)
        mm = np.clip(np.round(ranges * 1000), 0, MAX_RANGE_MM)
        return mm.astype("<u2")

    def produce(self, seq: int) -> bytes:
        """The msgpack input message for step ``seq``.

        Its size is 1050 bytes + len(robot) + 1, 2, 3 or 5 bytes for seq (< 128, < 256,
        < 65536, < 2**32): 1053-1055 bytes for robots "r1".."r9", and never more than the paper's
        1059 for robot names of up to 4 characters - the runtime refuses payloads larger than a
        chain's declared message size.
        """
        odom = self.odometry(seq)
        scan = self.scan_mm(seq)
        return pack({
            "v": INPUT_VERSION,
            "robot": self.robot,
            "seq": seq,
            "odom": [float(v) for v in odom],  # x_m, y_m, theta_rad in the odometry frame
            # Two 180-degree scanners (front, rear) of this many beams; readings of max_mm = no return.
            "laser": {"beams": BEAMS_PER_SCANNER, "max_mm": MAX_RANGE_MM},
            "front": scan[:BEAMS_PER_SCANNER].tobytes(),  # little-endian uint16 mm per beam
            "rear": scan[BEAMS_PER_SCANNER:].tobytes(),
        })

    def ground_truth(self, seq: int) -> dict[str, Any]:
        """``{"seq", "x_m", "y_m", "theta_rad"}``: where the robot really is at step ``seq``."""
        x, y, th = (float(v) for v in self.true_pose(seq))
        return {"seq": seq, "x_m": x, "y_m": y, "theta_rad": th}
