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


SLOW_EVERY = 100  # SlowEveryHundred computes for SLOW_BLOB_S on each instance's 101st, 201st, ... run
SLOW_BLOB_S = 2.0  # wall seconds: ~80 camera frames at x10 pile up behind it (its worker holds them)


class SlowEveryHundred:
    """paper-fig7's blob finder (same outputs: stateless), computing for `SLOW_BLOB_S` on runs
    `SLOW_EVERY` + 1, 2 * `SLOW_EVERY` + 1, ... of an instance (seqs 100, 200, ... of one that starts
    at 0; busy, as an overloaded stage is: not hung)."""

    def __init__(self, robot: str, seed: int):
        from autopower.chains.blobfinder import BlobFinder

        self.finder, self.runs = BlobFinder(robot), 0

    def run(self, payload: bytes) -> bytes:
        self.runs += 1
        if self.runs % SLOW_EVERY == 1 and self.runs > 1:  # its 101st run: seq 100 of a first instance
            until = time.monotonic() + SLOW_BLOB_S
            while time.monotonic() < until:
                pass
        return self.finder.run(payload)
