"""The small frames a robot keeps in custody, on disk too, so a crash of its process loses none.

Every frame a node produces stays in its custody (`autopower.agent.custody`) until its consumer
acknowledges it: a source's input for the next stage, a stage's output, the results it holds for
a sink out of its reach. That lived only in memory: a robot killed while cut off lost all of it
(random faults, seed 3: 532 Blob-2 results held by r2 for the base station, and 159 Loc-2 scans r2
kept for a stage on a robot it could not reach). So each frame of at most `MAX_KEPT_BYTES` is
appended here as it enters custody, and a restarted process of the same mission takes them back
into custody (`NodeRuntime.take_back_kept`), from where the consumers' reports get them resent.
Camera frames (230 kB) are not written: what a stage had not run yet at the kill is lost, like
the data of a sensor that was switched off.

The file is a journal: a header line naming the mission (its `resume.mission_key`), then one
record per frame: its length (4 bytes, little-endian) and the encoded `ChainFrame`. An append is
one ``write`` (~10 us); a kill leaves whole records and at most one torn last record, which is
skipped. Frames their consumers acknowledged are dropped by rewriting the file with those still
kept (`rewrite`, to a temporary file renamed over it) once most of it is done with, and it is
emptied when none is (`NodeRuntime.settle_kept`, at status ticks). Written 0600 beside the resume
state, in a 0700 directory.

A file that cannot be read is reported and ignored: the robot then starts with nothing kept, as
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
MAX_KEPT_BYTES = 64 * 1024  # frames with a larger payload (camera images) are kept in memory only


class KeptStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._fd: int | None = None
        self._mission: dict | None = None  # the mission the open journal belongs to
        self.records = 0  # records in the file now (what `rewrite` weighs against)
        self.failed = False

    def load(self, mission: dict) -> list[ChainFrame]:
        """The frames a crashed process of this mission kept (oldest first); [] for another mission."""
        try:
            data = self.path.read_bytes()
        except FileNotFoundError:
            return []
        except OSError as exc:
            log.warning("kept frames %s unreadable (%s); starting with none", self.path, exc)
            return []
        header, sep, body = data.partition(b"\n")
        try:
            if not sep or json.loads(header) != {"version": 1, "mission": mission}:
                return []  # another mission's (or not ours): nothing to carry on
        except (ValueError, UnicodeDecodeError):
            log.warning("kept frames %s have no valid header; starting with none", self.path)
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
                log.warning("kept frames %s: a damaged record skipped (%s)", self.path, exc)
        return frames

    def append(self, mission: dict, frame: ChainFrame) -> None:
        """One frame entered custody (one ``write``)."""
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
        """Keep only ``frames`` (those not acknowledged yet): the file replaced atomically, or emptied."""
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
        except OSError:
            os.close(fd)
            raise
        os.replace(self._tmp, self.path)
        if self._fd is not None:
            os.close(self._fd)
        os.lseek(fd, 0, os.SEEK_END)
        self._fd, self._mission, self.records = fd, dict(mission), len(frames)

    def _fail(self, exc: OSError) -> None:
        self.failed = True
        log.warning("kept frames not written to %s (%s): a crash would lose what this robot keeps", self.path, exc)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
