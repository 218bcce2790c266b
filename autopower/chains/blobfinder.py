"""A CMVision-style colour blob finder: PPM frame in, at most 200 bytes of blobs out.

Pipeline (as in CMVision, Bruce et al. 2000), vectorised with numpy:

1. classify every pixel into at most one colour class. Classes are boxes in YUV space; they
   are compiled once into a lookup table over RGB quantised to 5 bits per channel, so a frame
   costs one table lookup per pixel instead of a colour-space conversion;
2. run-length encode each row of the class image (runs of one class);
3. merge runs of the same class that overlap between consecutive rows (4-connectivity) into
   regions with a vectorised union-find (hooking + pointer jumping);
4. region statistics from the runs: area, centroid, bounding box; drop regions below the
   minimum area; sort largest first.

The output is a msgpack map; blobs are added largest first while the encoding still fits
``max_output_bytes`` (200 by default, the paper's output size), so the message never exceeds
it and ``"n"`` tells how many regions were found in total.

The finder is stateless; it still exports/imports an (empty) state so the runtime can treat
every component alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import msgpack
import numpy as np

from autopower.chains.base import ComponentStateError, MalformedInputError, unpack_map

OUTPUT_VERSION = 1
MAX_OUTPUT_BYTES = 200
MAX_IMAGE_SIDE_PX = 4096  # refuse absurd headers before allocating anything
_QUANT_BITS = 5  # bits kept per RGB channel in the classification table
_MAX_HEADER_BYTES = 1024  # comments included; stops a byte-by-byte scan of a garbage payload


@dataclass(frozen=True)
class ColourClass:
    """One colour to find: inclusive YUV ranges (BT.601, 0-255, U and V centred on 128)."""

    name: str
    y_range: tuple[int, int]
    u_range: tuple[int, int]
    v_range: tuple[int, int]


# Tuned for the saturated victim colours of autopower.chains.camera; low-saturation
# backgrounds have U and V near 128 and fall in none of them.
DEFAULT_CLASSES: tuple[ColourClass, ...] = (
    ColourClass("red", (30, 255), (60, 125), (185, 255)),
    ColourClass("green", (30, 255), (40, 110), (10, 90)),
    ColourClass("blue", (30, 255), (185, 255), (80, 135)),
    ColourClass("yellow", (30, 255), (0, 60), (125, 175)),
    ColourClass("magenta", (30, 255), (160, 230), (170, 245)),
    ColourClass("cyan", (30, 255), (135, 195), (0, 70)),
)


@dataclass(frozen=True)
class Blob:
    """One reported region: colour, area (px), centroid (px, sub-pixel), bbox (inclusive px)."""

    colour: str
    area_px: int
    x_px: float
    y_px: float
    bbox_px: tuple[int, int, int, int]  # x0, y0, x1, y1


@dataclass(frozen=True)
class BlobReport:
    """A decoded blob-finder output message."""

    width_px: int
    height_px: int
    n_found: int  # regions above the minimum area, including any not reported
    blobs: tuple[Blob, ...]  # largest first


def parse_ppm(data: bytes) -> np.ndarray:
    """Parse a binary PPM (P6, maxval 255) into an (H, W, 3) uint8 array (a view, no copy).

    Raises ``MalformedInputError`` (a ``ValueError``) naming what is wrong.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MalformedInputError(f"PPM: expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if data[:2] != b"P6":
        raise MalformedInputError(f"PPM: bad magic {data[:2]!r}, expected b'P6' (binary RGB PPM)")
    fields: list[int] = []
    pos = 2
    limit = min(len(data), _MAX_HEADER_BYTES)
    while len(fields) < 3:
        # Whitespace and '#' comments may separate header fields.
        while pos < limit and (data[pos:pos + 1].isspace() or data[pos:pos + 1] == b"#"):
            if data[pos:pos + 1] == b"#":
                end = data.find(b"\n", pos, limit)
                pos = limit if end < 0 else end + 1
            else:
                pos += 1
        if pos >= _MAX_HEADER_BYTES:
            raise MalformedInputError(f"PPM: header longer than {_MAX_HEADER_BYTES} bytes")
        start = pos
        while pos < limit and data[pos:pos + 1].isdigit():
            pos += 1
        if start == pos:
            names = ("width", "height", "maxval")
            got = data[start:start + 10]
            raise MalformedInputError(f"PPM: header field {names[len(fields)]} is not a number (got {got!r})")
        if pos - start > 6:
            raise MalformedInputError(f"PPM: header number {data[start:pos][:12]!r}... is too long")
        fields.append(int(data[start:pos]))
    width, height, maxval = fields
    if pos >= len(data) or not data[pos:pos + 1].isspace():
        raise MalformedInputError("PPM: header must end with one whitespace byte after maxval")
    pos += 1
    if maxval != 255:
        raise MalformedInputError(f"PPM: maxval {maxval} unsupported, only 8-bit (255) images")
    if not (1 <= width <= MAX_IMAGE_SIDE_PX and 1 <= height <= MAX_IMAGE_SIDE_PX):
        raise MalformedInputError(
            f"PPM: size {width}x{height} out of range (1..{MAX_IMAGE_SIDE_PX} px per side)")
    expected = width * height * 3
    got = len(data) - pos
    if got != expected:
        kind = "truncated" if got < expected else "has trailing bytes"
        raise MalformedInputError(
            f"PPM: raster {kind}: {width}x{height} RGB needs {expected} bytes after the "
            f"{pos}-byte header, got {got}")
    return np.frombuffer(data, dtype=np.uint8, count=expected, offset=pos).reshape(height, width, 3)


def build_class_table(classes: Sequence[ColourClass]) -> np.ndarray:
    """Compile YUV boxes into a (2**15,) uint8 table: quantised RGB index -> class (1-based, 0 = none).

    A colour in several boxes gets the first matching class, as in CMVision's priority order.
    """
    if not 1 <= len(classes) <= 255:
        raise ValueError(f"need 1..255 colour classes, got {len(classes)}")
    levels = 1 << _QUANT_BITS
    step = 256 // levels
    centres = np.arange(levels) * step + step // 2  # classify each bin by its centre colour
    r, g, b = np.meshgrid(centres, centres, centres, indexing="ij")
    y, u, v = _rgb_to_yuv(r.ravel(), g.ravel(), b.ravel())
    table = np.zeros(levels ** 3, dtype=np.uint8)
    for index, cls in reversed(list(enumerate(classes, start=1))):  # reversed: first class wins
        inside = ((cls.y_range[0] <= y) & (y <= cls.y_range[1]) & (cls.u_range[0] <= u) & (u <= cls.u_range[1])
                  & (cls.v_range[0] <= v) & (v <= cls.v_range[1]))
        table[inside] = index
    return table


def _rgb_to_yuv(r: np.ndarray, g: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer BT.601 RGB -> YUV with U, V offset to 128 (as a webcam driver delivers it)."""
    r, g, b = (np.asarray(c, dtype=np.int32) for c in (r, g, b))
    y = (77 * r + 150 * g + 29 * b) >> 8
    u = ((-43 * r - 85 * g + 128 * b) >> 8) + 128
    v = ((128 * r - 107 * g - 21 * b) >> 8) + 128
    return y, u, v


def classify(image: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Per-pixel class ids (uint8, 0 = no class) of an (H, W, 3) uint8 image."""
    q = image >> (8 - _QUANT_BITS)  # uint8: a third of the work of shifting 16-bit values
    # Built in place in one uint16 array (r, then g, then b shifted in), no temporaries per channel.
    index = q[..., 0].astype(np.uint16)
    index <<= _QUANT_BITS
    index |= q[..., 1]
    index <<= _QUANT_BITS
    index |= q[..., 2]
    return table.take(index)


Region = tuple[int, int, float, float, tuple[int, int, int, int]]  # class, area, x, y, bbox


def find_regions(class_image: np.ndarray, min_area_px: int) -> list[Region]:
    """Connected regions (4-connectivity) of equal non-zero class in a (H, W) uint8 image.

    Returns ``(class_id, area_px, x_px, y_px, (x0, y0, x1, y1))`` for every region with
    ``area_px >= min_area_px``, largest first (ties broken by class, then position). Centroids are
    of pixel centres (a pixel at column i has x = i + 0.5), matching the camera's ground truth.
    """
    height, width = class_image.shape
    stride = width + 1
    # A zero column after each row ends every run at the row's end, so one flat scan finds them.
    padded = np.zeros((height, stride), dtype=np.uint8)
    padded[:, :width] = class_image
    flat = padded.ravel()
    change = np.flatnonzero(np.diff(flat, prepend=np.uint8(0)))
    is_start = flat[change] != 0
    run_start = change[is_start]  # flat index of each run's first pixel
    # The run ends (exclusive) at the next change after its start; one always exists (sentinel).
    run_end = change[np.flatnonzero(is_start) + 1]
    if run_start.size == 0:
        return []
    run_class = flat[run_start]
    run_row = run_start // stride

    # For each run, the runs in the row above overlapping its columns form a contiguous index
    # range [lo, hi): runs are sorted by flat index and disjoint within a row.
    above_start = run_start - stride
    above_end = run_end - stride
    lo = np.searchsorted(run_end, above_start, side="right")
    hi = np.searchsorted(run_start, above_end, side="left")
    counts = np.maximum(hi - lo, 0)
    below = np.repeat(np.arange(run_start.size), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    above = np.repeat(lo, counts) + offsets
    same = run_class[below] == run_class[above]
    labels = _connected_labels(run_start.size, below[same], above[same])

    lengths = run_end - run_start
    col_start = run_start - run_row * stride
    _, region = np.unique(labels, return_inverse=True)
    n_regions = int(region.max()) + 1
    area = np.bincount(region, weights=lengths, minlength=n_regions)
    keep = np.flatnonzero(area >= min_area_px)
    if keep.size == 0:
        return []
    # Sum of pixel-centre x over a run [s, e) is len * (s + e) / 2.
    sum_x = np.bincount(region, weights=lengths * (col_start + col_start + lengths) / 2.0, minlength=n_regions)
    sum_y = np.bincount(region, weights=lengths * (run_row + 0.5), minlength=n_regions)
    x0 = np.full(n_regions, width, dtype=np.int64)
    y0 = np.full(n_regions, height, dtype=np.int64)
    x1 = np.full(n_regions, -1, dtype=np.int64)
    y1 = np.full(n_regions, -1, dtype=np.int64)
    np.minimum.at(x0, region, col_start)
    np.minimum.at(y0, region, run_row)
    np.maximum.at(x1, region, col_start + lengths - 1)
    np.maximum.at(y1, region, run_row)
    region_class = np.zeros(n_regions, dtype=np.int64)
    region_class[region] = run_class

    order = sorted(keep.tolist(), key=lambda k: (-area[k], region_class[k], y0[k], x0[k]))
    return [
        (int(region_class[k]), int(area[k]), float(sum_x[k] / area[k]), float(sum_y[k] / area[k]),
         (int(x0[k]), int(y0[k]), int(x1[k]), int(y1[k])))
        for k in order
    ]


def _connected_labels(n_nodes: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Component label (the smallest node id) of each node of an undirected graph given by edges a-b.

    Vectorised union-find: hook the larger root under the smaller one for every edge, then
    compress paths by pointer jumping; repeat until every edge joins equal labels. Pointers only
    ever decrease, so this stays a forest and converges in a few rounds for image regions.
    """
    parent = np.arange(n_nodes)
    while True:
        la, lb = parent[a], parent[b]
        differ = la != lb
        if not differ.any():
            return parent
        la, lb = la[differ], lb[differ]
        np.minimum.at(parent, np.maximum(la, lb), np.minimum(la, lb))
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped


class BlobFinder:
    """The "Blob" component: ``run(ppm_bytes) -> msgpack`` of up to ``max_output_bytes``."""

    component_type = "Blob"

    def __init__(self, robot: str = "", classes: Sequence[ColourClass] = DEFAULT_CLASSES,
                 min_area_px: int = 40, max_output_bytes: int = MAX_OUTPUT_BYTES) -> None:
        names = [c.name for c in classes]
        if len(set(names)) != len(names):
            raise ValueError(f"colour class names must be unique, got {names}")
        if max_output_bytes < 32:
            raise ValueError(f"max_output_bytes must be >= 32 to hold the header, got {max_output_bytes}")
        self.robot = robot
        self.classes = tuple(classes)
        self.min_area_px = min_area_px
        self.max_output_bytes = max_output_bytes
        self._table = build_class_table(self.classes)

    def find(self, image: np.ndarray) -> list[Blob]:
        """All regions of an (H, W, 3) uint8 image at or above the minimum area, largest first."""
        regions = find_regions(classify(image, self._table), self.min_area_px)
        return [Blob(self.classes[c - 1].name, area, x, y, bbox) for c, area, x, y, bbox in regions]

    def run(self, payload: bytes) -> bytes:
        """Find blobs in a PPM frame; return the msgpack output (always <= ``max_output_bytes``)."""
        image = parse_ppm(payload)
        blobs = self.find(image)
        return encode_report(image.shape[1], image.shape[0], blobs, self.max_output_bytes)

    def export_state(self) -> bytes:
        """The finder is stateless: an empty msgpack map."""
        return msgpack.packb({})

    def import_state(self, state: bytes) -> None:
        """Accept only the empty state ``export_state`` produces."""
        obj = unpack_map(state, "Blob state", ComponentStateError)
        if obj:
            raise ComponentStateError(
                f"Blob state: the blob finder is stateless, expected an empty map, got keys {sorted(obj)}")


def encode_report(width_px: int, height_px: int, blobs: Sequence[Blob], max_bytes: int = MAX_OUTPUT_BYTES) -> bytes:
    """Encode blobs (largest first) as msgpack, keeping as many as fit in ``max_bytes``.

    Layout: ``{"v": 1, "w": W, "h": H, "n": n_found, "b": [[colour, area, x, y, x0, y0, x1, y1], ...]}``
    with x, y as float32 (0.01 px resolution is plenty; float64 would cost 8 bytes more per blob).
    """
    def encode(k: int) -> bytes:
        rows = [[b.colour, b.area_px, b.x_px, b.y_px, *b.bbox_px] for b in blobs[:k]]
        return msgpack.packb({"v": OUTPUT_VERSION, "w": width_px, "h": height_px, "n": len(blobs), "b": rows},
                             use_single_float=True)

    # Blobs have similar sizes; grow until one more would not fit.
    out = encode(0)
    if len(out) > max_bytes:
        raise ValueError(f"max_bytes {max_bytes} cannot even hold the report header ({len(out)} bytes)")
    for k in range(1, len(blobs) + 1):
        candidate = encode(k)
        if len(candidate) > max_bytes:
            break
        out = candidate
    return out


def decode_report(data: bytes) -> BlobReport:
    """Decode a blob-finder output message (raises ``MalformedInputError`` if it is not one)."""
    obj = unpack_map(data, "Blob output")
    try:
        if obj["v"] != OUTPUT_VERSION:
            raise MalformedInputError(f"Blob output: version {obj['v']!r}, expected {OUTPUT_VERSION}")
        blobs = tuple(
            Blob(str(c), int(a), float(x), float(y), (int(x0), int(y0), int(x1), int(y1)))
            for c, a, x, y, x0, y0, x1, y1 in obj["b"]
        )
        return BlobReport(int(obj["w"]), int(obj["h"]), int(obj["n"]), blobs)
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, MalformedInputError):
            raise
        raise MalformedInputError(f"Blob output: bad layout ({exc!r})") from exc


def score_report(truth: dict[str, Any], output: bytes, tolerance_px: float = 3.0) -> dict[str, float]:
    """Compare a blob-finder output with a camera ground truth (``CameraSource.ground_truth``).

    A victim counts as found when a reported blob of its colour has its centroid within
    ``tolerance_px``. Returns victims_total, victims_found, false_blobs (reported blobs matching
    no victim) and max_centroid_error_px over found victims.
    """
    report = decode_report(output)
    victims = truth["victims"]
    matched: set[int] = set()
    errors: list[float] = []
    for victim in victims:
        best, best_err = None, math.inf
        for i, blob in enumerate(report.blobs):
            if blob.colour == victim["colour"] and i not in matched:
                err = math.hypot(blob.x_px - victim["x_px"], blob.y_px - victim["y_px"])
                if err < best_err:
                    best, best_err = i, err
        if best is not None and best_err <= tolerance_px:
            matched.add(best)
            errors.append(best_err)
    return {
        "victims_total": float(len(victims)),
        "victims_found": float(len(errors)),
        "false_blobs": float(len(report.blobs) - len(matched)),
        "max_centroid_error_px": max(errors) if errors else 0.0,
    }
