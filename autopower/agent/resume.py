"""What a restarted agent needs to carry on where it crashed: battery, mission, source positions.

The agent writes its resume state to a file of its own (0600, in the team's state directory:
``AUTOPOWER_STATE_DIR``, which the systemd units point at ``/var/lib/autopower``) at every
status tick, by atomic replace, and notes every frame a source produces in a journal next to
it (one short append: rewriting the file per frame cost ~2 ms on this machine's disk, the
append ~20 us). A process killed with SIGKILL loses nothing written before (the page cache
outlives it), so whoever restarts the
agent — `autopower up`'s supervisor or systemd's ``Restart=on-failure`` — gets a process that,
on the first plan of the *same* mission (same scenario and mission clock), takes its battery
from the file instead of the mission's starting energies (charging idle power for the time it
was down: the robot did not stop drawing current) and continues its sources' sequence numbers
(so the frames it produces next are neither taken for duplicates nor leave a gap). A plan of
another mission ignores the file.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

VERSION = 1
AGENTS_DIR = "agents"  # in the team's state directory: one resume file per agent, <robot>.json


class ResumeFile:
    """One agent's resume state on disk: a snapshot and a journal of source positions since it.

    Never raises: a robot runs on without it (a warning, once).
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.journal_path = self.path.with_name(self.path.name + ".journal")
        self._journal: int | None = None  # the open journal (append only)
        self._warned = False

    def load(self) -> dict | None:
        try:
            state = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            log.warning("resume state %s unreadable (%s); starting from the mission's energies", self.path, exc)
            return None
        if not isinstance(state, dict) or state.get("version") != VERSION:
            return None
        sources = state.get("sources")
        if isinstance(sources, dict):  # positions noted after the snapshot: the last one of each chain
            for chain, position in self._journal_entries():
                sources[chain] = position
        return state

    def _journal_entries(self) -> list[tuple[str, dict]]:
        try:
            lines = self.journal_path.read_text().splitlines()
        except (OSError, UnicodeDecodeError):
            return []
        out = []
        for line in lines:  # a line cut short by the crash is not valid JSON: skipped
            try:
                # a journal written before `missed_stopped` existed has five fields
                chain, run, seq, missed, total, *more = json.loads(line)
                out.append((str(chain), {"run": int(run), "seq": int(seq), "missed": int(missed),
                                         "produced_total": int(total),
                                         "missed_stopped": int(more[0]) if more else 0}))
            except (ValueError, TypeError):
                continue
        return out

    def save(self, state: dict) -> None:
        """The whole state (atomic replace); the journal starts again empty after it."""
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(json.dumps({"version": VERSION, **state}))
            os.replace(tmp, self.path)
            if self._journal is None:
                self._journal = os.open(self.journal_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            os.ftruncate(self._journal, 0)
        except OSError as exc:
            self._warn(exc)

    def note_source(self, chain: str, run: int, seq: int, missed: int, produced_total: int,
                    missed_stopped: int = 0) -> None:
        """A source moved on (its next seq): one append, before the frame leaves."""
        if self._journal is None:
            return  # no snapshot yet (before the mission): nothing to resume from anyway
        try:
            os.write(self._journal, (json.dumps([chain, run, seq, missed, produced_total, missed_stopped])
                                     + "\n").encode())
        except OSError as exc:
            self._warn(exc)

    def _warn(self, exc: OSError) -> None:
        if not self._warned:  # once: a full disk must not flood the log at the source's rate
            log.warning("resume state not written to %s (%s): a restart would reset the battery", self.path, exc)
            self._warned = True

    def close(self) -> None:
        if self._journal is not None:
            os.close(self._journal)
            self._journal = None
