"""The synthetic camera: exact PPM frames, determinism, moving victims that are really drawn."""

import numpy as np
import pytest

from autopower.chains.blobfinder import parse_ppm
from autopower.chains.camera import (
    FRAME_BYTES,
    HEIGHT_PX,
    PPM_HEADER,
    VICTIM_COLOURS_RGB,
    WIDTH_PX,
    CameraSource,
    SyntheticCamera,
)


def test_frame_is_the_papers_230415_byte_binary_ppm():
    frame = CameraSource("r2", seed=7).produce(0)
    assert len(frame) == FRAME_BYTES == 230415
    assert frame[:15] == PPM_HEADER == b"P6\n320 240\n255\n"
    assert parse_ppm(frame).shape == (HEIGHT_PX, WIDTH_PX, 3)


def test_frames_are_deterministic_in_robot_seed_and_seq():
    a, b = CameraSource("r2", seed=7), CameraSource("r2", seed=7)
    assert a.produce(3) == b.produce(3)
    assert a.ground_truth(3) == b.ground_truth(3)
    # Asking out of order changes nothing: a frame is a function of its index.
    assert a.produce(100) == CameraSource("r2", seed=7).produce(100)
    assert a.produce(3) != a.produce(4)
    assert a.produce(3) != CameraSource("r3", seed=7).produce(3)
    assert a.produce(3) != CameraSource("r2", seed=8).produce(3)


def test_victims_move_smoothly_between_frames():
    camera = SyntheticCamera(seed=11, n_victims=4)
    tracks = np.array([[(v.x_px, v.y_px) for v in camera.truth(f)] for f in range(60)])  # (frame, victim, xy)
    steps = np.linalg.norm(np.diff(tracks, axis=0), axis=2)
    assert (steps.sum(axis=0) > 20).all(), "every victim should travel over 60 frames"
    assert steps.max() < 10, "motion should be a few pixels per frame, not jumps"
    assert (steps[0] > 0).all(), "victims should move from frame 0 to frame 1"


@pytest.mark.parametrize("seed", range(6))
def test_victims_stay_in_frame_and_apart(seed):
    camera = SyntheticCamera(seed=seed, n_victims=6)
    for frame in (0, 17, 333):
        boxes = [v.bbox_px for v in camera.truth(frame)]
        for x0, y0, x1, y1 in boxes:
            assert 0 <= x0 <= x1 < WIDTH_PX and 0 <= y0 <= y1 < HEIGHT_PX
        for i, a in enumerate(boxes):
            for b in boxes[i + 1:]:
                gap_x = max(a[0], b[0]) - min(a[2], b[2])
                gap_y = max(a[1], b[1]) - min(a[3], b[3])
                assert max(gap_x, gap_y) > 2, f"victims {a} and {b} touch"


def test_victims_are_drawn_where_the_truth_says():
    camera = SyntheticCamera(seed=3, n_victims=5)
    image = camera.render(42).astype(int)
    for victim in camera.truth(42):
        pixel = image[int(victim.y_px), int(victim.x_px)]
        assert np.abs(pixel - VICTIM_COLOURS_RGB[victim.colour]).max() <= 8  # colour + sensor noise


def test_victim_colours_are_distinct_within_a_scene():
    colours = [v.colour for v in SyntheticCamera(seed=5, n_victims=6).truth(0)]
    assert sorted(colours) == sorted(VICTIM_COLOURS_RGB)


@pytest.mark.parametrize("bad", [0, 7, -1])
def test_victim_count_is_validated(bad):
    with pytest.raises(ValueError, match="n_victims"):
        SyntheticCamera(seed=1, n_victims=bad)


def test_negative_frame_is_rejected():
    with pytest.raises(ValueError, match="seq"):
        CameraSource("r1", seed=0).produce(-1)


def test_the_noise_offset_is_a_pure_function_of_seed_and_frame_and_covers_the_field():
    from autopower.chains.camera import _NOISE_MARGIN_PX, _noise_offset

    offsets = [_noise_offset(5, f) for f in range(100_000)]  # 4,225 windows: each drawn ~24 times
    assert offsets[:1000] == [_noise_offset(5, f) for f in range(1000)]
    assert all(0 <= dy <= _NOISE_MARGIN_PX and 0 <= dx <= _NOISE_MARGIN_PX for dy, dx in offsets)
    assert len(set(offsets)) == (_NOISE_MARGIN_PX + 1) ** 2  # every window of the field is used
    assert sum(a == b for a, b in zip(offsets, offsets[1:], strict=False)) < 100  # ~24 expected by chance  # consecutive frames' noise differs
    assert offsets[:50] != [_noise_offset(6, f) for f in range(50)]  # another camera, another noise
