"""Frame-difference motion detection: what changed since the previous frame, and where.

The output (20 bytes) is the step, how many pixels changed by more than ``THRESHOLD``, the centre
of those pixels, and the CRC-32 of the previous frame it compared against, so a sink can tell
whether the component had the right state. The state is that previous frame (or nothing before
the first one): ``export_state`` / ``import_state`` move it between hosts byte for byte.
"""

from __future__ import annotations

import struct
import zlib

from autopower import ComponentStateError, MalformedInputError

from motion_demo.camera import FRAME_BYTES, HEADER, MAGIC

THRESHOLD = 64  # grey levels: the noise flickers by less
OUTPUT = struct.Struct("<IIffI")  # seq, changed pixels, centre x, centre y, crc32(previous frame)
STATE_MAGIC = b"MDv1"


class MotionDetector:
    """The `autopower.StatefulComponent` protocol: ``run`` one frame, state = the previous frame."""

    SOURCE = "motion_demo.camera:GreyCamera"  # its input, for the entry point (pyproject.toml)

    def __init__(self, robot: str, seed: int):
        self.robot = robot
        self.previous: bytes | None = None

    def run(self, payload: bytes) -> bytes:
        if len(payload) != FRAME_BYTES or payload[:4] != MAGIC:
            raise MalformedInputError(f"motion: expected a {FRAME_BYTES}-byte GREY frame, got {len(payload)} bytes")
        _, width, _, seq = HEADER.unpack_from(payload)
        pixels = payload[HEADER.size:]
        previous = self.previous if self.previous is not None else pixels
        changed = sx = sy = 0
        for i, (a, b) in enumerate(zip(previous, pixels)):
            if abs(a - b) > THRESHOLD:
                changed += 1
                sx += i % width
                sy += i // width
        cx, cy = (sx / changed, sy / changed) if changed else (-1.0, -1.0)
        out = OUTPUT.pack(seq, changed, cx, cy, zlib.crc32(previous) if self.previous is not None else 0)
        self.previous = pixels
        return out

    def export_state(self) -> bytes:
        return STATE_MAGIC + (self.previous or b"")

    def import_state(self, state: bytes) -> None:
        if state[:4] != STATE_MAGIC or len(state) not in (4, 4 + FRAME_BYTES - HEADER.size):
            raise ComponentStateError(f"motion: not a MotionDetector state ({len(state)} bytes)")
        self.previous = bytes(state[4:]) or None


def decode(output: bytes) -> dict:
    """The detector's output as a dict (for tests and the operator's display)."""
    seq, changed, cx, cy, crc = OUTPUT.unpack(output)
    return {"seq": seq, "changed": changed, "x": cx, "y": cy, "previous_crc": crc}
