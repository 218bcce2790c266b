"""The "TeamMap" component: a fan-in stage merging every robot's localisation into one team map.

Its input is a *join message* (`encode_join`): for one step, the outputs of the stages that feed
it (each a "Loc" estimate, `autopower.chains.mcl`), keyed by producer stage, and the producers
whose output for that step is missing (late beyond the join bound or lost; docs/concepts/chains.md).
It keeps, per robot, the latest pose and the explored area: the cells of a 0.5 m grid
within the laser's reach of each estimated pose, weighted by how sure the estimate is (a pose
whose position sigma exceeds 1 m marks nothing). Its output, <= 2,000 B: each robot's pose,
sigma, age and explored area, and the team's explored-cells bitmap (40 x 40 cells, 200 B).

The state (grids, poses) survives `export_state`/`import_state`: the stage migrates with it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from autopower.chains.base import (
    ComponentStateError,
    MalformedInputError,
    pack,
    require_fields,
    unpack_map,
)
from autopower.chains.mcl import N_REPORTED_PARTICLES, OUTPUT_VERSION as MCL_OUTPUT_VERSION, decode_estimate
from autopower.chains.world import SIZE_M, LocSource

JOIN_VERSION = 1
OUTPUT_VERSION = 1
STATE_VERSION = 1
CELL_M = 0.5
CELLS = int(round(SIZE_M / CELL_M))  # 40 x 40
REACH_M = 2.0  # what the lasers reliably see around the robot (their 8 m range is mostly walls)
MAX_SIGMA_M = 1.0  # an estimate less sure than this marks no explored cells
MAX_ROBOTS = 64


def encode_join(step: int, inputs: dict[str, bytes], missing: list[str]) -> bytes:
    """The input of a fan-in stage for one step: the producers' outputs and who is missing."""
    return pack({"v": JOIN_VERSION, "step": int(step), "inputs": {k: bytes(v) for k, v in inputs.items()},
                 "missing": sorted(missing)})


def decode_join(data: bytes) -> dict[str, Any]:
    what = "join message"
    obj = unpack_map(data, what)
    require_fields(obj, {"v": int, "step": int, "inputs": dict, "missing": list}, what)
    if obj["v"] != JOIN_VERSION:
        raise MalformedInputError(f"{what}: version {obj['v']}, expected {JOIN_VERSION}")
    if not all(isinstance(k, str) and isinstance(v, bytes) for k, v in obj["inputs"].items()):
        raise MalformedInputError(f"{what}: inputs must map stage names to bytes")
    if not all(isinstance(m, str) for m in obj["missing"]):
        raise MalformedInputError(f"{what}: missing must be a list of stage names")
    return obj


class JoinSource:
    """The input a TeamMap gets when its producers are "Loc" stages: for profiling and tests only.

    A fan-in stage has no sensor of its own (the runtime never starts this as a source); this
    builds, for step ``seq``, the join of three robots' localisation outputs placed at their true
    poses (``LocSource.ground_truth``) with a 0.1 m position sigma, in the "Loc" output format.
    """

    ROBOTS = ("r1", "r2", "r3")

    def __init__(self, robot: str, seed: int) -> None:
        self.robot = robot
        self._truth = {r: LocSource(r, seed) for r in self.ROBOTS}

    def produce(self, seq: int) -> bytes:
        inputs = {}
        for k, (robot, source) in enumerate(self._truth.items()):
            t = source.ground_truth(seq)
            cov = [0.005, 0.0, 0.0, 0.0, 0.005, 0.0, 0.0, 0.0, 0.001]
            inputs[f"Loc-{k + 1}"] = pack({"v": MCL_OUTPUT_VERSION, "robot": robot, "seq": seq,
                                          "pose": [t["x_m"], t["y_m"], t["theta_rad"]], "cov": cov,
                                          "n_eff": 1000.0, "top": bytes(16 * N_REPORTED_PARTICLES)})
        return encode_join(seq, inputs, [])


class TeamMap:
    """Merges the robots' pose estimates of each step into per-robot explored grids and poses."""

    def __init__(self, robot: str, seed: int) -> None:
        self.robot = robot
        self._grids: dict[str, np.ndarray] = {}  # robot -> bool (CELLS, CELLS), row = y
        self._poses: dict[str, list[float]] = {}  # robot -> [x, y, theta, sigma_m, step]
        self.steps = 0
        self.missed = 0  # inputs that were missing when their step was joined
        centres = (np.arange(CELLS) + 0.5) * CELL_M
        self._cx, self._cy = np.meshgrid(centres, centres)

    def run(self, payload: bytes) -> bytes:
        join = decode_join(payload)
        step = join["step"]
        for _stage, data in sorted(join["inputs"].items()):
            est = decode_estimate(data)
            if est.robot not in self._grids and len(self._grids) >= MAX_ROBOTS:
                raise MalformedInputError(f"TeamMap: more than {MAX_ROBOTS} robots")
            x, y, theta = est.pose
            sigma = math.sqrt(max(0.0, float(est.covariance[0, 0] + est.covariance[1, 1])))
            grid = self._grids.setdefault(est.robot, np.zeros((CELLS, CELLS), dtype=bool))
            if sigma <= MAX_SIGMA_M:
                grid |= (self._cx - x) ** 2 + (self._cy - y) ** 2 <= REACH_M ** 2
            self._poses[est.robot] = [x, y, theta, sigma, float(step)]
        self.steps += 1
        self.missed += len(join["missing"])
        team = np.zeros((CELLS, CELLS), dtype=bool)
        for grid in self._grids.values():
            team |= grid
        area = CELL_M * CELL_M
        return pack({
            "v": OUTPUT_VERSION, "step": step, "missing": join["missing"],
            "robots": {r: {"pose": p[:3], "sigma_m": p[3], "age_steps": step - int(p[4]),
                           "explored_m2": float(self._grids[r].sum()) * area}
                       for r, p in sorted(self._poses.items())},
            "explored_m2": float(team.sum()) * area,
            "grid": np.packbits(team).tobytes(),  # CELLS x CELLS bits, row-major, row 0 = y 0
        })

    def export_state(self) -> bytes:
        return pack({"v": STATE_VERSION, "steps": self.steps, "missed": self.missed,
                     "grids": {r: np.packbits(g).tobytes() for r, g in self._grids.items()},
                     "poses": self._poses})

    def import_state(self, state: bytes) -> None:
        what = "TeamMap state"
        obj = unpack_map(state, what, ComponentStateError)
        require_fields(obj, {"v": int, "steps": int, "missed": int, "grids": dict, "poses": dict}, what,
                       ComponentStateError)
        if obj["v"] != STATE_VERSION:
            raise ComponentStateError(f"{what}: version {obj['v']}, expected {STATE_VERSION}")
        grids, poses = {}, {}
        for robot, bits in obj["grids"].items():
            if not isinstance(bits, bytes) or len(bits) != CELLS * CELLS // 8 or robot not in obj["poses"]:
                raise ComponentStateError(f"{what}: bad grid for {robot!r}")
            grids[robot] = np.unpackbits(np.frombuffer(bits, dtype=np.uint8)).astype(bool).reshape(CELLS, CELLS)
            pose = obj["poses"][robot]
            if not (isinstance(pose, list) and len(pose) == 5 and all(isinstance(v, (int, float)) for v in pose)):
                raise ComponentStateError(f"{what}: bad pose for {robot!r}")
            poses[robot] = [float(v) for v in pose]
        self._grids, self._poses = grids, poses
        self.steps, self.missed = obj["steps"], obj["missed"]


def decode_map(data: bytes) -> dict[str, Any]:
    """Decode a TeamMap output (raises ``MalformedInputError`` if it is not one)."""
    what = "TeamMap output"
    obj = unpack_map(data, what)
    require_fields(obj, {"v": int, "step": int, "missing": list, "robots": dict, "explored_m2": float,
                         "grid": bytes}, what)
    if obj["v"] != OUTPUT_VERSION or len(obj["grid"]) != CELLS * CELLS // 8:
        raise MalformedInputError(f"{what}: bad layout")
    return obj


def score_map(truth: dict[str, Any], output: bytes) -> dict[str, float]:
    """What the map holds (it has no ground truth of its own): robots merged and area explored."""
    out = decode_map(output)
    return {"robots": float(len(out["robots"])), "explored_m2": out["explored_m2"]}
