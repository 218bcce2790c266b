"""A synthetic 320x240 camera looking at a floor with a few brightly coloured "victims".

The scene is a textured, low-saturation background (floor tiles, shading, dull clutter, a few
tiny saturated specks the blob finder must ignore) with 1-6 victims: filled discs or rectangles
of distinct saturated colours that move deterministically (a Lissajous path per victim). Each
victim moves inside its own cell of a 3x2 grid, so victims never touch or occlude each other
and the ground-truth centre of a victim is also the centroid a perfect blob finder reports.

Frames are binary PPM (P6): a 15-byte header plus 230400 bytes of RGB = 230415 bytes, the
blob finder's input size in the AutoPower paper (Fig. 5). Everything is a function of
(seed, frame index); rendering one frame takes ~2 ms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from autopower.chains.base import check_seed, check_seq, robot_key

WIDTH_PX = 320
HEIGHT_PX = 240
PPM_HEADER = b"P6\n%d %d\n255\n" % (WIDTH_PX, HEIGHT_PX)
FRAME_BYTES = len(PPM_HEADER) + WIDTH_PX * HEIGHT_PX * 3  # 230415

# Saturated victim colours (RGB). Their YUV chroma is far from the grey background's, which is
# what the blob finder's default colour classes rely on.
VICTIM_COLOURS_RGB: dict[str, tuple[int, int, int]] = {
    "red": (220, 30, 30),
    "green": (30, 200, 40),
    "blue": (30, 40, 220),
    "yellow": (230, 220, 30),
    "magenta": (220, 30, 220),
    "cyan": (30, 210, 220),
}
MAX_VICTIMS = len(VICTIM_COLOURS_RGB)

_GRID_COLS, _GRID_ROWS = 3, 2
_CELL_W_PX = WIDTH_PX / _GRID_COLS
_CELL_H_PX = HEIGHT_PX / _GRID_ROWS
_MARGIN_PX = 4.0  # keep victims this far from their cell's edges (and so from each other)
_NOISE_LEVELS = 8  # per-channel uniform pixel noise in [-8, +8]
# Sensor noise is cut per frame from a larger field drawn once per camera, at an offset drawn per
# frame: drawing 230,400 fresh random numbers took 0.5 of the 0.85 ms a frame cost (x50: 400 frames a second).
_NOISE_MARGIN_PX = 64
_MASK64 = (1 << 64) - 1


def _noise_offset(seed: int, frame: int) -> tuple[int, int]:
    """Frame ``frame``'s (dy, dx) into the noise field: splitmix64 of (seed, frame), a few
    microseconds in Python where seeding a numpy generator per frame took 0.14 of a frame's 0.88 ms."""
    z = (seed * 0x9E3779B97F4A7C15 + frame * 0xD1B54A32D192ED03 + 0x9015E) & _MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    z ^= z >> 31
    return (z & 0xFFFFFFFF) % (_NOISE_MARGIN_PX + 1), (z >> 32) % (_NOISE_MARGIN_PX + 1)


@dataclass(frozen=True)
class VictimTruth:
    """Where a victim is in one frame: centre (px, sub-pixel), pixel area and bounding box."""

    colour: str
    shape: str  # "disc" or "rect"
    x_px: float
    y_px: float
    area_px: int
    bbox_px: tuple[int, int, int, int]  # x0, y0, x1, y1 inclusive

    def as_dict(self) -> dict[str, Any]:
        """Plain-data form (msgpack/JSON-able)."""
        return {
            "colour": self.colour, "shape": self.shape, "x_px": self.x_px, "y_px": self.y_px,
            "area_px": self.area_px, "bbox_px": list(self.bbox_px),
        }


@dataclass(frozen=True)
class _Victim:
    colour: str
    shape: str
    half_w_px: float  # disc radius, or rectangle half-width
    half_h_px: float  # disc radius, or rectangle half-height
    cell_cx_px: float
    cell_cy_px: float
    amp_x_px: float
    amp_y_px: float
    period_x_frames: float
    period_y_frames: float
    phase_x_rad: float
    phase_y_rad: float

    def centre_at(self, frame: int) -> tuple[float, float]:
        x = self.cell_cx_px + self.amp_x_px * math.sin(2 * math.pi * frame / self.period_x_frames + self.phase_x_rad)
        y = self.cell_cy_px + self.amp_y_px * math.sin(2 * math.pi * frame / self.period_y_frames + self.phase_y_rad)
        return x, y

    def mask(self, x_px: float, y_px: float) -> tuple[int, int, np.ndarray]:
        """Rasterise at centre (x, y): return (x0, y0, boolean mask) of the covered pixels.

        A pixel is covered when its centre (i + 0.5) lies inside the shape, so the mask's
        centroid matches the analytic centre to well under a pixel.
        """
        x0 = int(math.floor(x_px - self.half_w_px))
        y0 = int(math.floor(y_px - self.half_h_px))
        x1 = int(math.ceil(x_px + self.half_w_px))
        y1 = int(math.ceil(y_px + self.half_h_px))
        xs = np.arange(x0, x1 + 1) + 0.5 - x_px
        ys = np.arange(y0, y1 + 1) + 0.5 - y_px
        if self.shape == "disc":
            inside = (xs[None, :] ** 2 + ys[:, None] ** 2) <= self.half_w_px ** 2
        else:
            inside = (np.abs(xs)[None, :] <= self.half_w_px) & (np.abs(ys)[:, None] <= self.half_h_px)
        return x0, y0, inside


class SyntheticCamera:
    """Renders frames of a seeded scene; ``frame(i)`` and ``truth(i)`` are pure functions of i."""

    def __init__(self, seed: int, n_victims: int = 4) -> None:
        check_seed(seed)
        if not 1 <= n_victims <= MAX_VICTIMS:
            raise ValueError(f"n_victims must be 1..{MAX_VICTIMS}, got {n_victims}")
        self.seed = seed
        self.n_victims = n_victims
        rng = np.random.default_rng([seed, 0xCA3E7A])
        self._victims = _make_victims(rng, n_victims)
        self._background = _make_background(rng)
        h, w, c = self._background.shape
        self._noise = (np.random.default_rng([seed, 0x9015E]).integers(
            0, 2 * _NOISE_LEVELS + 1, size=(h + _NOISE_MARGIN_PX, w + _NOISE_MARGIN_PX, c), dtype=np.int16)
            - np.int16(_NOISE_LEVELS))

    def truth(self, frame: int) -> list[VictimTruth]:
        """Ground truth for every victim in frame ``frame``."""
        check_seq(frame)
        out = []
        for victim in self._victims:
            x, y = victim.centre_at(frame)
            x0, y0, mask = victim.mask(x, y)
            rows, cols = np.nonzero(mask)
            out.append(VictimTruth(
                colour=victim.colour, shape=victim.shape, x_px=x, y_px=y, area_px=int(mask.sum()),
                bbox_px=(x0 + int(cols.min()), y0 + int(rows.min()), x0 + int(cols.max()), y0 + int(rows.max())),
            ))
        return out

    def render(self, frame: int) -> np.ndarray:
        """The RGB image of frame ``frame`` as a (240, 320, 3) uint8 array."""
        image = np.empty(self._background.shape, dtype=np.uint8)
        self._render_into(frame, image)
        return image

    def _render_into(self, frame: int, out: np.ndarray) -> None:
        check_seq(frame)
        image = self._background.copy()
        for victim in self._victims:
            x, y = victim.centre_at(frame)
            x0, y0, mask = victim.mask(x, y)
            h, w = mask.shape
            image[y0:y0 + h, x0:x0 + w][mask] = VICTIM_COLOURS_RGB[victim.colour]
        # Sensor noise, different in every frame and reproducible from (seed, frame), computed in place
        dy, dx = _noise_offset(self.seed, frame)
        h, w, _ = image.shape
        noisy = self._noise[dy:dy + h, dx:dx + w] + image  # int16
        np.clip(noisy, 0, 255, out=out, casting="unsafe")

    def frame(self, frame: int) -> bytes:
        """Frame ``frame`` as a 230415-byte binary PPM."""
        h, w, _ = self._background.shape
        header = b"P6\n%d %d\n255\n" % (w, h)  # what encode_ppm writes, around the pixels rendered in place
        buf = np.empty(len(header) + h * w * 3, dtype=np.uint8)
        buf[:len(header)] = np.frombuffer(header, dtype=np.uint8)
        self._render_into(frame, buf[len(header):].reshape(h, w, 3))
        return buf.tobytes()


def encode_ppm(image: np.ndarray) -> bytes:
    """Encode an (H, W, 3) uint8 RGB array as binary PPM (P6, maxval 255)."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    h, w, _ = image.shape
    return b"P6\n%d %d\n255\n" % (w, h) + np.ascontiguousarray(image).tobytes()


def _make_victims(rng: np.random.Generator, n_victims: int) -> list[_Victim]:
    colours = rng.permutation(list(VICTIM_COLOURS_RGB))[:n_victims]
    cells = rng.permutation(_GRID_COLS * _GRID_ROWS)[:n_victims]
    victims = []
    for colour, cell in zip(colours, cells, strict=True):
        shape = "disc" if rng.random() < 0.5 else "rect"
        if shape == "disc":
            half_w = half_h = float(rng.uniform(9.0, 18.0))
        else:
            half_w, half_h = (float(v) for v in rng.uniform(8.0, 18.0, size=2))
        col, row = int(cell) % _GRID_COLS, int(cell) // _GRID_COLS
        # The shape plus its swing must stay inside the cell, minus a margin.
        amp_x = max(0.0, _CELL_W_PX / 2 - half_w - _MARGIN_PX - 1.0)
        amp_y = max(0.0, _CELL_H_PX / 2 - half_h - _MARGIN_PX - 1.0)
        victims.append(_Victim(
            colour=str(colour), shape=shape, half_w_px=half_w, half_h_px=half_h,
            cell_cx_px=(col + 0.5) * _CELL_W_PX, cell_cy_px=(row + 0.5) * _CELL_H_PX,
            amp_x_px=amp_x * float(rng.uniform(0.5, 1.0)), amp_y_px=amp_y * float(rng.uniform(0.5, 1.0)),
            # 20-80 frames per swing = 5-20 s at the paper's 4 frames/s: a few px per frame.
            period_x_frames=float(rng.uniform(20.0, 80.0)), period_y_frames=float(rng.uniform(20.0, 80.0)),
            phase_x_rad=float(rng.uniform(0, 2 * math.pi)), phase_y_rad=float(rng.uniform(0, 2 * math.pi)),
        ))
    return victims


def _make_background(rng: np.random.Generator) -> np.ndarray:
    """A static floor: beige-grey tiles with grout, soft shading, dull boxes and tiny specks."""
    ys, xs = np.mgrid[0:HEIGHT_PX, 0:WIDTH_PX].astype(np.float64)
    base = np.array([125.0, 118.0, 108.0]) + rng.uniform(-10, 10, size=3)
    # Brightness-only variation (same offset on R, G, B) keeps the chroma low everywhere.
    fx, fy, px, py = rng.uniform(0.01, 0.04), rng.uniform(0.01, 0.04), *rng.uniform(0, 2 * math.pi, 2)
    shade = 22.0 * np.sin(fx * xs + px) * np.cos(fy * ys + py) - 0.08 * ys
    tile_px = int(rng.integers(32, 48))
    grout = ((xs % tile_px) < 2) | ((ys % tile_px) < 2)
    shade = shade - 30.0 * grout
    image = base[None, None, :] + shade[..., None]
    # Dull clutter (boxes, a mat) in low-saturation colours that no victim class matches.
    for _ in range(int(rng.integers(3, 7))):
        w, h = rng.integers(15, 60, size=2)
        x0, y0 = int(rng.integers(0, WIDTH_PX - w)), int(rng.integers(0, HEIGHT_PX - h))
        grey = float(rng.uniform(70, 170))
        tint = rng.uniform(-12, 12, size=3)
        image[y0:y0 + h, x0:x0 + w] = grey + tint
    image = np.clip(image, 0, 255)
    # Tiny saturated specks (4-9 px): a blob finder must drop them by area, not report them.
    colours = list(VICTIM_COLOURS_RGB.values())
    for _ in range(12):
        size = int(rng.integers(2, 4))
        x0, y0 = int(rng.integers(0, WIDTH_PX - size)), int(rng.integers(0, HEIGHT_PX - size))
        image[y0:y0 + size, x0:x0 + size] = colours[int(rng.integers(len(colours)))]
    return image.astype(np.uint8)


class CameraSource:
    """The "Blob" chain's source: one robot's camera, ``produce(seq)`` = PPM of frame ``seq``."""

    component_type = "Blob"

    def __init__(self, robot: str, seed: int, n_victims: int = 4) -> None:
        self.robot = robot
        self.seed = seed
        # Each robot sees its own scene: mix the robot into the scene seed.
        self.camera = SyntheticCamera(seed=(check_seed(seed) << 32) | robot_key(robot), n_victims=n_victims)

    def produce(self, seq: int) -> bytes:
        """The 230415-byte PPM frame for step ``seq``."""
        return self.camera.frame(seq)

    def ground_truth(self, seq: int) -> dict[str, Any]:
        """``{"frame": seq, "victims": [VictimTruth.as_dict(), ...]}``."""
        return {"frame": seq, "victims": [v.as_dict() for v in self.camera.truth(seq)]}
