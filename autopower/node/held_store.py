"""Results a robot holds for a sink out of its reach, kept on disk so a crash does not lose them.

A robot cut off from a chain's sink holds the chain's results (`Holds.hold`, within
the hold budget, scenario `[delivery] hold_budget_mb`) until the sink is back. Held only in memory, they would
all be lost with a robot killed while cut off. So each held result is appended here as it is
held, and a restarted process of the same mission takes them back (`load`), holds them again
and sends them once the sink is in reach; custody then keeps them until the sink acknowledges.

The file is a snapshot and journal generations (`runtime.snapshot_journal`: the loop only appends
to an open file; creating, renaming and removing files is the writer's, a thread of its own in a
live node). The snapshot is a header line naming the mission (its `resume.mission_key`) and the
journal generation that follows it, then records; each generation holds records only. A record is
the encoded `ChainFrame`'s length (4 bytes, little-endian) and the encoded frame. An append is one
``write``; a kill leaves whole records and at most one torn last record per file, which is
skipped. Results the sink acknowledged are dropped by a new snapshot of those still at risk
(`rewrite`) when most of the file is done with, and by an empty one when none is; a rewrite the
writer has not finished yet is skipped (the next status tick tries again) and the file then holds
more than is at risk, never less. Written 0600 beside the resume state. Results are small (a pose,
a list of blobs), and only held results are written: the camera frames in custody are not.

A file that cannot be read is reported and ignored: the robot then starts with nothing held, as
it did before this existed. Nothing here raises.
"""

from __future__ import annotations

import json
import logging
import struct
from pathlib import Path

from autopower.errors import ProtocolError
from autopower.protocol import ChainFrame, decode, encode
from autopower.runtime.snapshot_journal import SnapshotJournal

log = logging.getLogger(__name__)

_LENGTH = struct.Struct("<I")
MAX_RECORD_BYTES = 64 * 2**20  # a length above this is garbage (a frame's payload is bounded the same way)
VERSION = 2  # version 1: one file, no generations (still read)
MISSION_SWITCH_WAIT_S = 2.0  # how long a new mission's first snapshot may hold the caller (once a mission)


class HeldStore:
    def __init__(self, path: str | Path, *, background: bool = False):
        self.path = Path(path)
        self._files = SnapshotJournal(self.path, background=background, on_error=self._fail)
        self._mission: dict | None = None  # the mission of the last snapshot handed to the writer
        self._waited_for: dict | None = None  # the mission whose first snapshot the caller already waited for
        self.records = 0  # records in the snapshot and its journals now (what `rewrite` weighs against)
        self.failed = False

    def load(self, mission: dict) -> list[ChainFrame]:
        """The results a crashed process of this mission held (oldest first); [] for another mission."""
        try:
            data = self._files.read_snapshot()
        except OSError as exc:
            log.warning("held results %s unreadable (%s); starting with none held", self.path, exc)
            return []
        if data is None:
            return []
        header, sep, body = data.partition(b"\n")
        try:
            fields = json.loads(header)
            if not sep or not isinstance(fields, dict) or fields.get("mission") != mission:
                return []  # another mission's (or not ours): nothing to carry on
            if fields.get("version") == 1:
                journals = []  # one file, no generations
            elif fields.get("version") == VERSION and isinstance(fields.get("journal"), int):
                journals = self._files.journals_since(fields["journal"])
            else:
                return []
        except (ValueError, UnicodeDecodeError):
            log.warning("held results %s have no valid header; starting with none held", self.path)
            return []
        return [frame for part in (body, *journals) for frame in self._records(part)]

    def _records(self, data: bytes) -> list[ChainFrame]:
        frames, offset = [], 0
        while offset + _LENGTH.size <= len(data):
            (size,) = _LENGTH.unpack_from(data, offset)
            record = data[offset + _LENGTH.size:offset + _LENGTH.size + size]
            if size > MAX_RECORD_BYTES or len(record) < size:
                break  # the torn last record of a kill (or garbage): what came before stands
            offset += _LENGTH.size + size
            try:
                frames.append(decode(record, ChainFrame))
            except ProtocolError as exc:
                log.warning("held results %s: a damaged record skipped (%s)", self.path, exc)
        return frames

    def append(self, mission: dict, frame: ChainFrame) -> bool:
        """One result held now (one ``write``); whether it is on disk."""
        if self.failed:
            return False
        if mission != self._mission and not self.rewrite(mission, []):
            return False
        if not self._files.append(_record(frame)):
            return False
        self.records += 1
        return True

    def rewrite(self, mission: dict, frames: list[ChainFrame]) -> bool:
        """Keep only ``frames`` (those still at risk); False if skipped (the writer is behind) or failed.

        The first snapshot of a mission waits for one still being written (at most
        `MISSION_SWITCH_WAIT_S`, once per mission: a writer stuck longer must not hold the loop
        at every held result): what is appended after it belongs to the new mission."""
        if self.failed:
            return False

        def content(generation: int) -> bytes:
            header = json.dumps({"version": VERSION, "mission": mission, "journal": generation}).encode()
            return b"".join([header, b"\n", *(_record(f) for f in frames)])

        switching = mission != self._mission
        first_try = switching and mission != self._waited_for
        if first_try:
            self._waited_for = dict(mission)
        if not self._files.snapshot(content, wait_s=MISSION_SWITCH_WAIT_S if first_try else 0.0):
            if first_try and not self.failed:
                log.warning("held results %s: the writer is still behind; results held now are not on disk",
                            self.path)
            return False
        self._mission, self.records = dict(mission), len(frames)
        return True

    def _fail(self, exc: OSError) -> None:
        self.failed = True
        log.warning("held results not written to %s (%s): a crash would lose what this robot holds", self.path, exc)

    def close(self) -> None:
        self._files.close()


def _record(frame: ChainFrame) -> bytes:
    encoded = encode(frame)
    return _LENGTH.pack(len(encoded)) + encoded
