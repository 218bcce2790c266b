"""A sink's ledgers kept on disk, so a restarted sink neither repeats nor loses an output.

The base station is the operator's sink. When it is killed and started again, the producers'
custody (`autopower.node.custody`) resends every output the old sink had not acknowledged yet
(acknowledgements travel in the status, every half second), including some it had received:
without its ledgers the new sink would hand those to the operator a second time. So the sink
notes every new output it takes in and writes the notes out (`commit`) just before the status that
acknowledges them (the recording of those outputs is written at the same moment and never sooner,
`Recorder.flush_outputs`); the restarted sink rebuilds its ledgers from the notes, counts the
resent copies as redundant and reports the same prefix to the producers. An output taken in after
the last status is neither noted nor acknowledged nor recorded when the process dies: custody
resends it and the new sink delivers and records it once (noting it at once instead would lose it
from the recording, whose buffer dies with the process, while the new sink takes the resend for a
copy).

The file is a journal: a header naming the mission (its clock's ``epoch_unix``: another mission
starts empty), a snapshot of the ledgers (`SinkLedger.state`), then one line per new output
(chain, run, seq, CRC-32 of its data: what the ledger and its digest need). Appending a line is
one ``write`` (microseconds; rewriting a file per output cost milliseconds here, as the filesystem
flushes on truncate and rename); a kill at any instant leaves whole lines and at most one torn
last line, which is skipped. When the journal grows past ``COMPACT_BYTES`` it is rewritten as a
snapshot (to a temporary file renamed over it). A file that cannot be read is reported and
ignored: the sink then starts empty.

Each commit's notes end with a marker line (``{"commit": n}``). The notes are written before the
recording is flushed, so a kill between the two leaves outputs delivered and noted whose recording
died with the process; the resent copies are redundant to the new sink and are not recorded again,
so the recording would miss outputs the operator has. Only the last commit can be in that window
(each flush comes before the next commit), and the markers say where it starts: `load` gives its
outputs as `last_batch`, and the restarted sink logs them to the recording
(`SinkListener.sink_journal`), so replay does not count them as lost. Noting after the flush
instead would turn the same window into duplicates delivered to the operator.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from autopower.node.sequencing import SinkLedger

log = logging.getLogger(__name__)

COMPACT_BYTES = 4 * 1024 * 1024  # ~100,000 outputs between snapshots


class SinkStore:
    def __init__(self, path: Path, compact_bytes: int = COMPACT_BYTES):
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self.compact_bytes = compact_bytes
        self._fd: int | None = None
        self._mission: float | None = None  # the mission the open journal belongs to
        self._size = 0
        self.failed = False  # a write failed (reported once; the sink goes on without)
        self._pending: list[bytes] = []  # notes taken since the last commit
        self._rewrite_due: tuple[float, dict[str, SinkLedger]] | None = None
        self._commits = 0
        # after `load`: the outputs the crashed sink's last commit noted, (chain, run, seq) each
        self.last_batch: list[tuple[str, int, int]] = []

    # ---- reading -----------------------------------------------------------------------------
    def load(self, mission_epoch_unix: float) -> dict[str, SinkLedger]:
        """The ledgers kept for this mission ({} for another mission, none kept, or a bad file)."""
        try:
            lines = self.path.read_bytes().split(b"\n")
        except FileNotFoundError:
            return {}
        except OSError as exc:
            log.warning("sink state %s is unreadable (%s); starting the sinks empty", self.path, exc)
            return {}
        try:
            header = json.loads(lines[0])
            if not isinstance(header, dict) or header.get("mission_epoch_unix") != mission_epoch_unix:
                return {}  # another mission's (or a file we did not write)
            ledgers = {str(c): SinkLedger.from_state(s) for c, s in json.loads(lines[1])["sinks"].items()}
        except (IndexError, KeyError, TypeError, ValueError, AttributeError, UnicodeDecodeError) as exc:
            log.warning("sink state %s is not a sink state (%s); starting the sinks empty", self.path, exc)
            return {}
        replayed = 0
        closed: list[tuple[str, int, int]] = []  # the notes of the last commit whose marker is written
        trailing: list[tuple[str, int, int]] = []  # the notes after the last marker
        for number, line in enumerate(lines[2:], start=3):
            if not line:
                continue
            try:
                note = json.loads(line)
                if isinstance(note, dict) and "commit" in note:
                    closed, trailing = trailing, []
                    continue
                chain, run, seq, crc = note
                ledgers.setdefault(str(chain), SinkLedger()).record(int(run), int(seq), crc=int(crc))
                trailing.append((str(chain), int(run), int(seq)))
                replayed += 1
            except (TypeError, ValueError, UnicodeDecodeError):
                if number < len(lines) - 1:  # only the last line may be torn (a kill mid-write)
                    log.warning("sink state %s: line %d is damaged; skipped", self.path, number)
        # a kill while the last commit was written leaves notes after the last marker: that commit's
        # (older files, without markers, give every note after the snapshot)
        self.last_batch = trailing or closed
        log.info("sinks go on from %s (%d output(s) after its snapshot): %s", self.path, replayed,
                 ", ".join(f"{c} run {l.run} seq {l.contiguous}" for c, l in sorted(ledgers.items())) or "none")
        return ledgers

    # ---- writing -----------------------------------------------------------------------------
    def keep(self, mission_epoch_unix: float, sinks: dict[str, SinkLedger], chain: str, run: int, seq: int,
             crc: int) -> None:
        """Note a new output (already recorded in ``sinks[chain]``); written out by `commit`."""
        if self.failed:
            return
        if self._fd is None or self._mission != mission_epoch_unix or self._size >= self.compact_bytes:
            self._rewrite_due = (mission_epoch_unix, sinks)  # a snapshot at commit includes this output
            self._pending.clear()
            return
        if self._rewrite_due is None:
            self._pending.append(json.dumps([chain, run, seq, crc], separators=(",", ":")).encode() + b"\n")

    def commit(self) -> None:
        """Write the notes taken since the last commit (one ``write``); called before each status."""
        if self.failed or (self._rewrite_due is None and not self._pending):
            return
        try:
            if self._rewrite_due is not None:
                mission, sinks = self._rewrite_due
                self._rewrite_due = None
                self._rewrite(mission, sinks)
                return
            self._commits += 1
            marker = json.dumps({"commit": self._commits}, separators=(",", ":")).encode() + b"\n"
            lines, self._pending = b"".join(self._pending) + marker, []
            os.write(self._fd, lines)
            self._size += len(lines)
        except OSError as exc:
            log.error("cannot keep the sink state in %s (%s); a restart may repeat outputs", self.path, exc)
            self.failed = True

    def _rewrite(self, mission_epoch_unix: float, sinks: dict[str, SinkLedger]) -> None:
        header = json.dumps({"mission_epoch_unix": mission_epoch_unix}).encode()
        snapshot = json.dumps({"sinks": {c: l.state() for c, l in sinks.items()}}, separators=(",", ":")).encode()
        fd = os.open(self._tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, header + b"\n" + snapshot + b"\n")
        finally:
            os.close(fd)
        os.replace(self._tmp, self.path)
        if self._fd is not None:
            os.close(self._fd)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        self._mission = mission_epoch_unix
        self._size = len(header) + len(snapshot) + 2

    def close(self, *, commit: bool = True) -> None:
        """``commit=False``: closed as a killed process leaves it (the notes since the last commit are lost)."""
        if commit:
            self.commit()
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
