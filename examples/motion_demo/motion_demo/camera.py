"""The chain's input: a 64x48 greyscale frame per step, deterministic in (robot, seed, seq)."""

from __future__ import annotations

import random
import struct
import zlib

WIDTH, HEIGHT = 64, 48
MAGIC = b"GREY"
HEADER = struct.Struct("<4sHHI")  # magic, width, height, seq
FRAME_BYTES = HEADER.size + WIDTH * HEIGHT  # 3084
SQUARE = 8  # side of the moving object, pixels


class GreyCamera:
    """A fixed camera watching one bright square cross a noisy scene (the `autopower.Source` protocol)."""

    def __init__(self, robot: str, seed: int):
        self.robot = robot
        # str hash() differs between processes: derive the scene from stable numbers only
        self._key = zlib.crc32(robot.encode()) ^ seed
        rng = random.Random(self._key)
        self._background = bytes(rng.randrange(20, 60) for _ in range(WIDTH * HEIGHT))
        self._speed = (rng.choice((1, 2, 3)), rng.choice((-2, -1, 1, 2)))

    def object_at(self, seq: int) -> tuple[int, int]:
        """Top-left corner of the square at step ``seq`` (it bounces off the edges)."""
        return _bounce(seq * self._speed[0], WIDTH - SQUARE), _bounce(7 + seq * self._speed[1], HEIGHT - SQUARE)

    def produce(self, seq: int) -> bytes:
        pixels = bytearray(self._background)
        noise = random.Random(self._key * 1_000_003 + seq)
        for _ in range(40):  # sensor noise: a few pixels flicker
            pixels[noise.randrange(WIDTH * HEIGHT)] = noise.randrange(20, 60)
        x0, y0 = self.object_at(seq)
        for y in range(y0, y0 + SQUARE):
            pixels[y * WIDTH + x0: y * WIDTH + x0 + SQUARE] = b"\xe0" * SQUARE
        return HEADER.pack(MAGIC, WIDTH, HEIGHT, seq) + bytes(pixels)

    def ground_truth(self, seq: int) -> dict:
        x0, y0 = self.object_at(seq)
        return {"x": x0 + SQUARE / 2, "y": y0 + SQUARE / 2}


def _bounce(position: int, span: int) -> int:
    position %= 2 * span
    return position if position <= span else 2 * span - position
