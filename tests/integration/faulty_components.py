"""Plug-in components that misbehave, for the live failure tests (imported by the agents)."""

from __future__ import annotations

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
