"""The blob finder: finds every victim, never exceeds 200 bytes, rejects malformed frames."""

import statistics
import time
from collections import deque

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.chains.base import ComponentStateError, MalformedInputError
from autopower.chains.blobfinder import (
    MAX_OUTPUT_BYTES,
    Blob,
    BlobFinder,
    decode_report,
    encode_report,
    find_regions,
    parse_ppm,
    score_report,
)
from autopower.chains.camera import FRAME_BYTES, CameraSource, SyntheticCamera, encode_ppm

FINDER = BlobFinder()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31), n_victims=st.integers(1, 6), frame=st.integers(0, 10_000))
def test_finds_every_victim_of_the_ground_truth(seed, n_victims, frame):
    camera = SyntheticCamera(seed=seed, n_victims=n_victims)
    out = FINDER.run(camera.frame(frame))
    assert len(out) <= MAX_OUTPUT_BYTES
    report = decode_report(out)
    truth = camera.truth(frame)
    assert report.n_found == len(truth), "tiny specks and the background must not be reported"
    assert len(report.blobs) == len(truth), "up to 6 victims fit in 200 bytes"
    by_colour = {b.colour: b for b in report.blobs}
    for victim in truth:
        blob = by_colour[victim.colour]
        assert abs(blob.x_px - victim.x_px) < 1.0 and abs(blob.y_px - victim.y_px) < 1.0
        # Only specks of its colour touching the victim can add pixels: at most 9 each, and two
        # may touch it (seed 2_069_776_675, 3 victims, frame 198: +12 px, found by hypothesis).
        assert victim.area_px <= blob.area_px <= victim.area_px + 2 * 9
        assert all(abs(a - b) <= 3 for a, b in zip(blob.bbox_px, victim.bbox_px, strict=True))
    assert [b.area_px for b in report.blobs] == sorted((b.area_px for b in report.blobs), reverse=True)


def test_score_report_matches_the_source_truth():
    source = CameraSource("r3", seed=1)
    scores = score_report(source.ground_truth(9), FINDER.run(source.produce(9)))
    assert scores["victims_found"] == scores["victims_total"] == 4
    assert scores["false_blobs"] == 0 and scores["max_centroid_error_px"] < 1.0
    # A report for another frame misses victims (they moved): scoring can fail.
    wrong = score_report(source.ground_truth(9), FINDER.run(source.produce(40)))
    assert wrong["victims_found"] < 4


def _reference_regions(class_image: np.ndarray, min_area: int) -> set:
    """Plain breadth-first flood fill, 4-connectivity: the obviously-correct version."""
    h, w = class_image.shape
    seen = np.zeros_like(class_image, dtype=bool)
    regions = set()
    for y in range(h):
        for x in range(w):
            c = class_image[y, x]
            if c == 0 or seen[y, x]:
                continue
            pixels, queue = [], deque([(y, x)])
            seen[y, x] = True
            while queue:
                py, px = queue.popleft()
                pixels.append((py, px))
                for ny, nx in ((py + 1, px), (py - 1, px), (py, px + 1), (py, px - 1)):
                    if 0 <= ny < h and 0 <= nx < w and not seen[ny, nx] and class_image[ny, nx] == c:
                        seen[ny, nx] = True
                        queue.append((ny, nx))
            if len(pixels) >= min_area:
                ys, xs = np.array(pixels).T
                regions.add((int(c), len(pixels), round(float(xs.mean()) + 0.5, 6), round(float(ys.mean()) + 0.5, 6),
                             (int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max()))))
    return regions


@settings(max_examples=150, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shape=st.tuples(st.integers(1, 14), st.integers(1, 17)),
       n_classes=st.integers(1, 3), density=st.floats(0.2, 0.9), min_area=st.integers(1, 4))
def test_connected_regions_match_a_flood_fill(seed, shape, n_classes, density, min_area):
    rng = np.random.default_rng(seed)
    image = np.where(rng.random(shape) < density, rng.integers(1, n_classes + 1, shape), 0).astype(np.uint8)
    got = {(c, a, round(x, 6), round(y, 6), bbox) for c, a, x, y, bbox in find_regions(image, min_area)}
    assert got == _reference_regions(image, min_area)


def test_spiral_region_needing_many_merges_is_one_blob():
    # A spiral forces merges that only connect far down the image: a single pass would split it.
    image = np.zeros((21, 21), dtype=np.uint8)
    top, left, bottom, right = 0, 0, 20, 20
    while top <= bottom and left <= right:
        image[top, left:right + 1] = 1
        image[top:bottom + 1, right] = 1
        image[bottom, left:right + 1] = 1
        image[top + 2:bottom + 1, left] = 1
        top, left, bottom, right = top + 2, left + 2, bottom - 2, right - 2
        if top <= bottom:
            image[top - 1, left] = 1  # link the next ring to this one
    regions = find_regions(image, 1)
    assert len(regions) == len(_reference_regions(image, 1)) == 1
    assert regions[0][1] == int(image.sum())


def _blocks_image(rng: np.random.Generator, n_blocks: int) -> np.ndarray:
    image = np.full((240, 320, 3), 120, dtype=np.uint8)
    colours = [(220, 30, 30), (30, 200, 40), (30, 40, 220), (230, 220, 30)]
    for _ in range(n_blocks):
        w, h = rng.integers(3, 40, size=2)
        x, y = rng.integers(0, 320 - w), rng.integers(0, 240 - h)
        image[y:y + h, x:x + w] = colours[rng.integers(len(colours))]
    return image


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_blocks=st.integers(0, 120))
def test_output_never_exceeds_200_bytes_and_keeps_the_largest(seed, n_blocks):
    image = _blocks_image(np.random.default_rng(seed), n_blocks)
    out = FINDER.run(encode_ppm(image))
    assert len(out) <= MAX_OUTPUT_BYTES
    report = decode_report(out)
    everything = FINDER.find(image)
    assert report.n_found == len(everything)
    assert [b.area_px for b in report.blobs] == [b.area_px for b in everything[:len(report.blobs)]]


def test_cap_drops_the_smallest_blobs_and_fills_the_budget():
    image = np.full((240, 320, 3), 120, dtype=np.uint8)
    for i in range(20):  # 20 red squares of distinct sizes, 8x8 .. 27x27
        side = 8 + i
        x, y = (i % 5) * 62 + 2, (i // 5) * 58 + 2
        image[y:y + side, x:x + side] = (220, 30, 30)
    out = FINDER.run(encode_ppm(image))
    report = decode_report(out)
    assert report.n_found == 20
    kept = len(report.blobs)
    assert 0 < kept < 20 and len(out) <= 200
    assert [b.area_px for b in report.blobs] == [(27 - i) ** 2 for i in range(kept)]
    # One more blob would not have fitted: the cap is the byte budget, not a fixed count.
    everything = FINDER.find(image)
    assert len(encode_report(320, 240, everything[:kept + 1], max_bytes=10_000)) > 200


def test_report_round_trips():
    blobs = [Blob("red", 500, 10.25, 20.5, (1, 2, 30, 40)), Blob("cyan", 60, 300.75, 200.0, (295, 195, 305, 205))]
    report = decode_report(encode_report(320, 240, blobs))
    assert report.blobs == tuple(blobs) and report.n_found == 2 and (report.width_px, report.height_px) == (320, 240)


def test_comments_in_the_ppm_header_are_allowed():
    frame = SyntheticCamera(seed=1).frame(0)
    commented = b"P6\n# a webcam\n320 240 # size\n255\n" + frame[15:]
    assert np.array_equal(parse_ppm(commented), parse_ppm(frame))


_GOOD = SyntheticCamera(seed=1).frame(0)
_RASTER = _GOOD[15:]


@pytest.mark.parametrize(("payload", "message"), [
    (b"", "bad magic"),
    (b"P3\n320 240\n255\n" + _RASTER, "bad magic"),
    (b"\x89PNG\r\n\x1a\n" + _RASTER, "bad magic"),
    (b"P6\n320\n", "height is not a number"),
    (b"P6\nabc 240\n255\n" + _RASTER, "width is not a number"),
    (b"P6\n320 240\n65535\n" + _RASTER, "maxval 65535 unsupported"),
    (b"P6\n0 240\n255\n", "out of range"),
    (b"P6\n99999 99999\n255\n", "out of range"),
    (_GOOD[:-1], "truncated"),
    (_GOOD[:15], "truncated"),
    (_GOOD + b"\x00", "trailing bytes"),
    (b"P6\n320 240\n255", "one whitespace byte"),
    (b"P6" + b" " * 5000, "header longer"),
    ("P6\n320 240\n255\n", "expected bytes"),
])
def test_malformed_ppm_is_rejected_with_a_clear_value_error(payload, message):
    with pytest.raises(ValueError, match=message) as excinfo:
        FINDER.run(payload)
    assert isinstance(excinfo.value, MalformedInputError)
    assert str(excinfo.value).startswith("PPM: ")


def test_stateless_but_same_interface_as_mcl():
    assert FINDER.component_type == "Blob"
    state = FINDER.export_state()
    assert msgpack.unpackb(state) == {}
    BlobFinder().import_state(state)
    with pytest.raises(ComponentStateError, match="stateless"):
        FINDER.import_state(msgpack.packb({"particles": b"x"}))
    with pytest.raises(ValueError, match="not valid msgpack"):
        FINDER.import_state(b"\xc1")


def test_frame_latency_is_well_under_20_ms():
    source = CameraSource("r2", seed=4)
    frames = [source.produce(seq) for seq in range(20)]
    finder = BlobFinder()
    latencies = []
    for frame in frames:
        start = time.perf_counter()
        finder.run(frame)
        latencies.append(time.perf_counter() - start)
    assert len(frames[0]) == FRAME_BYTES
    assert statistics.median(latencies) < 0.020


def test_every_pixel_gets_the_class_of_its_colour_box_in_yuv():
    # classify builds a 15-bit index in place and looks it up; check it pixel by pixel against
    # the class boxes themselves, for every 8-bit value of each channel (a random image, and a
    # ramp through all 256 levels so every quantisation bin and its edges are hit).
    from autopower.chains.blobfinder import DEFAULT_CLASSES, _rgb_to_yuv, build_class_table, classify

    rng = np.random.default_rng(11)
    ramp = np.stack(np.meshgrid(np.arange(256), np.arange(0, 256, 3), indexing="ij"), axis=-1)
    ramp = np.concatenate([ramp, ramp[..., :1][:, ::-1]], axis=-1).astype(np.uint8)  # (256, 86, 3)
    image = np.concatenate([ramp, rng.integers(0, 256, size=(256, 64, 3), dtype=np.uint8)], axis=1)
    got = classify(image, build_class_table(DEFAULT_CLASSES))
    # Each pixel is classified by the centre of its 5-bit bin, the first matching box winning.
    centre = (image.astype(np.int32) >> 3) * 8 + 4
    y, u, v = _rgb_to_yuv(centre[..., 0], centre[..., 1], centre[..., 2])
    expected = np.zeros(image.shape[:2], dtype=np.uint8)
    for index, cls in reversed(list(enumerate(DEFAULT_CLASSES, start=1))):
        inside = ((cls.y_range[0] <= y) & (y <= cls.y_range[1]) & (cls.u_range[0] <= u) & (u <= cls.u_range[1])
                  & (cls.v_range[0] <= v) & (v <= cls.v_range[1]))
        expected[inside] = index
    assert np.array_equal(got, expected)
    assert len(np.unique(got)) == len(DEFAULT_CLASSES) + 1  # the test image reaches every class
