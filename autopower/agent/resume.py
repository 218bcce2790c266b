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

The event loop never waits for the file system's metadata (`runtime.snapshot_journal`): a live
agent's snapshot is written by a thread of its own (`background=True`), and the source positions
go to journal generations the loop only appends to; a snapshot the thread has not finished yet is
skipped, and the next status brings a newer one. Nothing noted is ever lost.

The plan a robot runs lists the team's stages and links (28 kB at 300 robots) and changes far less
often than its battery: it goes to a side file of the snapshot (`SnapshotJournal`), named by its
hash and written only when it changed; each snapshot names it (``plan_file``), and a load puts it
back in the state's ``plan``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
from pathlib import Path

from autopower.runtime.snapshot_journal import SnapshotJournal

log = logging.getLogger(__name__)

VERSION = 1
AGENTS_DIR = "agents"  # in the team's state directory: one resume file per agent, <robot>.json
_PLAN_FILE = re.compile(r"[0-9a-f]{32}")  # a plan's side file: the hash of its text


class ResumeFile:
    """One agent's resume state on disk: a snapshot and journals of source positions since it.

    Never raises: a robot runs on without it (a warning, once).
    """

    def __init__(self, path: str | Path, *, background: bool = False):
        self.path = Path(path)
        self.journal_path = self.path.with_name(self.path.name + ".journal")  # before generations
        self._files = SnapshotJournal(self.path, background=background, on_error=self._warn,
                                      supersedes=(self.journal_path,))
        self._plan: tuple[str, str, bytes] | None = None  # (plan text, its side file's name, its bytes)

    @property
    def current_journal(self) -> Path:
        """The journal generation the notes go to now."""
        return self._files.current_journal

    @property
    def skipped(self) -> int:
        """Snapshots not written because the one before was still being written."""
        return self._files.skipped

    def load(self) -> dict | None:
        try:
            state = json.loads(self._files.read_snapshot() or b"null")
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            log.warning("resume state %s unreadable (%s); starting from the mission's energies", self.path, exc)
            return None
        if not isinstance(state, dict) or state.get("version") != VERSION:
            return None
        name = state.pop("plan_file", None)
        if isinstance(name, str) and _PLAN_FILE.fullmatch(name):
            try:
                state["plan"] = self._files.side_path(name).read_bytes().decode("ascii")
            except (OSError, UnicodeDecodeError) as exc:
                log.warning("resume state %s: plan %s unreadable (%s)", self.path, name, exc)
                state["plan"] = None
        sources = state.get("sources")
        if isinstance(sources, dict):  # positions noted after the snapshot: the last one of each chain
            since = state.get("journal")
            if isinstance(since, int):
                journals = self._files.journals_since(since)
            else:  # written before generations
                try:
                    journals = [self.journal_path.read_bytes()]
                except OSError:
                    journals = []
            for journal in journals:
                for chain, position in self._journal_entries(journal):
                    sources[chain] = position
        return state

    @staticmethod
    def _journal_entries(journal: bytes) -> list[tuple[str, dict]]:
        out = []
        for line in journal.splitlines():  # a line cut short by the crash is not valid JSON: skipped
            try:
                # a journal written before `missed_stopped` existed has five fields
                chain, run, seq, missed, total, *more = json.loads(line)
                out.append((str(chain), {"run": int(run), "seq": int(seq), "missed": int(missed),
                                         "produced_total": int(total),
                                         "missed_stopped": int(more[0]) if more else 0}))
            except (ValueError, TypeError, UnicodeDecodeError):
                continue
        return out

    def save(self, state: dict, *, wait_s: float = 0.0) -> bool:
        """Hand the whole state to the writer (written at once without a thread); False if skipped.

        The notes from now on go to a new journal generation, which the snapshot names.
        ``wait_s``: how long to wait for a snapshot still being written (the last one before the
        process ends), instead of skipping.
        """
        side = None
        plan = state.get("plan")
        if isinstance(plan, str):  # the plan to its side file, written when it changed (the module's rule)
            if self._plan is None or self._plan[0] is not plan and self._plan[0] != plan:
                data = plan.encode("ascii")
                self._plan = (plan, hashlib.blake2b(data, digest_size=16).hexdigest(), data)
            side = self._plan[1:]
            state = {**state, "plan": None, "plan_file": self._plan[1]}
        return self._files.snapshot(lambda generation: json.dumps({"version": VERSION, **state,
                                                                  "journal": generation}).encode(), wait_s=wait_s,
                                    side=side)

    def written(self, timeout_s: float) -> bool:
        """Wait until no snapshot is being written (at most `timeout_s`); whether none is."""
        return self._files.written(timeout_s)

    def note_source(self, chain: str, run: int, seq: int, missed: int, produced_total: int,
                    missed_stopped: int = 0) -> None:
        """A source moved on (its next seq): one append, before the frame leaves (a restarted process
        appends before its first snapshot too: the next restart reads it after its predecessor's)."""
        self._files.append((json.dumps([chain, run, seq, missed, produced_total, missed_stopped]) + "\n").encode())

    def _warn(self, exc: OSError) -> None:
        log.warning("resume state not written to %s (%s): a restart would reset the battery", self.path, exc)

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is pending (waiting at most `timeout_s` for the writer), then close the journals."""
        self._files.close(timeout_s)
