"""Plug-in components that misbehave, for the live failure tests (imported by the agents)."""

from __future__ import annotations

import time

from motion_demo.motion import MotionDetector


class RaisesAtTen(MotionDetector):
    """The worked example's detector, until its 10th frame."""

    def run(self, payload: bytes) -> bytes:
        if int.from_bytes(payload[8:12], "little") == 10:
            raise ValueError("RaisesAtTen: frame 10 is the end of the world")
        return super().run(payload)


class SpinsAtTen(MotionDetector):
    """The worked example's detector, until its 10th frame: then it computes for ever."""

    def run(self, payload: bytes) -> bytes:
        if int.from_bytes(payload[8:12], "little") == 10:
            while True:
                pass
        return super().run(payload)


SLOW_FRAMES = range(100, 104)  # the frames it takes long over: a bounded overload, well after the start
SLOW_S = 1.5  # wall seconds of CPU per slow frame: longer than a peer waits for a status (1 s)


class SlowAtHundred(MotionDetector):
    """The worked example's detector, computing for `SLOW_S` on each of `SLOW_FRAMES` (same outputs)."""

    def run(self, payload: bytes) -> bytes:
        if int.from_bytes(payload[8:12], "little") in SLOW_FRAMES:
            until = time.monotonic() + SLOW_S
            while time.monotonic() < until:  # busy, as an overloaded stage is (not blocked: not hung)
                pass
        return super().run(payload)
