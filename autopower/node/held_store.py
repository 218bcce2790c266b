"""Results a robot holds for a sink out of its reach, kept on disk so a crash does not lose them.

A robot cut off from a chain's sink holds the chain's results (`NodeRuntime.hold_output`, within
the hold budget, scenario `[delivery] hold_budget_mb`) until the sink is back. Held only in memory, they would
all be lost with a robot killed while cut off. So each held result is appended here as it is
held, and a restarted process of the same mission takes them back (`load`), holds them again
and sends them once the sink is in reach; custody then keeps them until the sink acknowledges.

The file is a journal: a header line naming the mission (its `resume.mission_key`), then one
record per held result: its length (4 bytes, little-endian) and the encoded `ChainFrame`. An
append is one ``write``; a kill leaves whole records and at most one torn last record, which is
skipped. Results the sink acknowledged are dropped by rewriting the file with those still at risk
(`rewrite`, to a temporary file renamed over it) when most of it is done with, and it is emptied
when none is. Written 0600 beside the resume state. Results are small (a pose, a list of blobs),
and only held results are written: the camera frames in custody are not.

A file that cannot be read is reported and ignored: the robot then starts with nothing held, as
it did before this existed. Nothing here raises.
"""

from __future__ import annotations

import json
import logging
import os
import struct
from pathlib import Path

from autopower.errors import ProtocolError
from autopower.protocol import ChainFrame, decode, encode

log = logging.getLogger(__name__)

_LENGTH = struct.Struct("<I")
MAX_RECORD_BYTES = 64 * 2**20  # a length above this is garbage (a frame's payload is bounded the same way)


class HeldStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._fd: int | None = None
        self._mission: dict | None = None  # the mission the open journal belongs to
        self.records = 0  # records in the file now (what `rewrite` weighs against)
        self.failed = False

    def load(self, mission: dict) -> list[ChainFrame]:
        """The results a crashed process of this mission held (oldest first); [] for another mission."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return []
        except OSError as exc:
            log.warning("held results %s unreadable (%s); starting with none held", self.path, exc)
            return []
        header, sep, body = data.partition(b"\n")
        try:
            if not sep or json.loads(header) != {"version": 1, "mission": mission}:
                return []  # another mission's (or not ours): nothing to carry on
        except (ValueError, UnicodeDecodeError):
            log.warning("held results %s have no valid header; starting with none held", self.path)
            return []
        frames, offset = [], 0
        while offset + _LENGTH.size <= len(body):
            (size,) = _LENGTH.unpack_from(body, offset)
            record = body[offset + _LENGTH.size:offset + _LENGTH.size + size]
            if size > MAX_RECORD_BYTES or len(record) < size:
                break  # the torn last record of a kill (or garbage): what came before stands
            offset += _LENGTH.size + size
            try:
                frames.append(decode(record, ChainFrame))
            except ProtocolError as exc:
                log.warning("held results %s: a damaged record skipped (%s)", self.path, exc)
        return frames

    def append(self, mission: dict, frame: ChainFrame) -> None:
        """One result held now (one ``write``)."""
        if self.failed:
            return
        try:
            if self._fd is None or mission != self._mission:
                self._start(mission, [])
            record = encode(frame)
            os.write(self._fd, _LENGTH.pack(len(record)) + record)
            self.records += 1
        except OSError as exc:
            self._fail(exc)

    def rewrite(self, mission: dict, frames: list[ChainFrame]) -> None:
        """Keep only ``frames`` (those still at risk): the file replaced atomically, or emptied."""
        if self.failed:
            return
        try:
            self._start(mission, frames)
        except OSError as exc:
            self._fail(exc)

    def _start(self, mission: dict, frames: list[ChainFrame]) -> None:
        self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(self._tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, json.dumps({"version": 1, "mission": mission}).encode() + b"\n")
            for frame in frames:
                record = encode(frame)
                os.write(fd, _LENGTH.pack(len(record)) + record)
            os.replace(self._tmp, self.path)
        except OSError:
            os.close(fd)  # a failed write or rename must not leak the descriptor
            raise
        if self._fd is not None:
            os.close(self._fd)
        os.lseek(fd, 0, os.SEEK_END)
        self._fd, self._mission, self.records = fd, dict(mission), len(frames)

    def _fail(self, exc: OSError) -> None:
        self.failed = True
        log.warning("held results not written to %s (%s): a crash would lose what this robot holds", self.path, exc)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
