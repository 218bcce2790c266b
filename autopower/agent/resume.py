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

Rule: the event loop never waits for the file system's metadata. Creating, renaming, truncating
and unlinking files wait for the file system's journal, and under a burst of writes by anything
else on the machine they took 1-2 s each (two robots' loops stopped together, missing a second of
source periods). So a live agent's snapshot is written by a thread of its own (`background=True`),
and the source journal is split in generations (`<name>.journal.<g>`) the loop only appends to:
a snapshot says from which generation on the journals hold what came after it; the thread, once
the snapshot is in place, removes the older generations and creates the next one empty, which the
loop takes at its next snapshot. While the thread is behind, the loop skips that snapshot (a
newer one follows at the next status) and keeps appending: nothing noted is ever lost. Without
the thread (`background=False`, the simulator) the same steps run at once, in the caller.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from pathlib import Path

log = logging.getLogger(__name__)

VERSION = 1
AGENTS_DIR = "agents"  # in the team's state directory: one resume file per agent, <robot>.json


class ResumeFile:
    """One agent's resume state on disk: a snapshot and journals of source positions since it.

    Never raises: a robot runs on without it (a warning, once).
    """

    def __init__(self, path: str | Path, *, background: bool = False):
        self.path = Path(path)
        self.journal_path = self.path.with_name(self.path.name + ".journal")  # before generations
        self._journal: int | None = None  # the open journal generation the loop appends to
        self._generation = 0
        self._warned = False
        self._cond = threading.Condition()
        self._spare: tuple[int, int] | None = None  # (generation, fd): created ahead by the writer
        # a snapshot (its generation, its text: serialised by the caller, who owns the state) and the
        # journal fd it retires
        self._pending: tuple[int, str, int | None] | None = None
        self._closing = False
        self.skipped = 0  # snapshots not written because the one before was still being written
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name=f"resume {self.path.name}", daemon=True)
            self._thread.start()

    @property
    def current_journal(self) -> Path:
        """The journal generation the notes go to now."""
        return self.generation_path(self._generation)

    def generation_path(self, generation: int) -> Path:
        return self.path.with_name(f"{self.path.name}.journal.{generation}")

    def _generations(self) -> list[int]:
        prefix = self.path.name + ".journal."
        try:
            names = [p.name for p in self.path.parent.iterdir()]
        except OSError:
            return []
        return sorted(int(n[len(prefix):]) for n in names if n.startswith(prefix) and n[len(prefix):].isdigit())

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
            since = state.get("journal")
            paths = ([self.journal_path] if not isinstance(since, int)  # written before generations
                     else [self.generation_path(g) for g in self._generations() if g >= since])
            for path in paths:
                for chain, position in self._journal_entries(path):
                    sources[chain] = position
        return state

    @staticmethod
    def _journal_entries(path: Path) -> list[tuple[str, dict]]:
        try:
            lines = path.read_text().splitlines()
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

    def save(self, state: dict, *, wait_s: float = 0.0) -> bool:
        """Hand the whole state to the writer (written at once without a thread); False if skipped.

        The notes from now on go to a new journal generation, which the snapshot names: a load
        applies that generation and the later ones on top of it. ``wait_s``: how long to wait for
        a snapshot still being written (the last one before the process ends), instead of skipping.
        """
        with self._cond:
            if wait_s > 0 and self._thread is not None:
                self._cond.wait_for(lambda: self._pending is None, timeout=wait_s)
            if self._pending is not None or self._closing:
                self.skipped += 1  # the writer is behind: the next status brings a newer snapshot
                return False
            if self._spare is not None:
                spare, self._spare = self._spare, None
            else:  # the first snapshot, or the writer could not create the next generation: here, once
                opened = self._open_next()
                if opened is None:
                    return False
                spare = opened
            retired = self._journal
            self._generation, self._journal = spare
            text = json.dumps({"version": VERSION, **state, "journal": self._generation})
            self._pending = (self._generation, text, retired)
            self._cond.notify()
        if self._thread is None:
            self._write_pending()
        return True

    def written(self, timeout_s: float) -> bool:
        """Wait until no snapshot is being written (at most `timeout_s`); whether none is."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None, timeout=timeout_s)

    def _open_next(self) -> tuple[int, int] | None:
        generation = max(self._generations() + [self._generation], default=0) + 1  # after any left on disk
        try:
            self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            return generation, self._create(generation)
        except OSError as exc:
            self._warn(exc)
            return None

    def _create(self, generation: int) -> int:
        return os.open(self.generation_path(generation), os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o600)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                if self._pending is None:
                    return
            self._write_pending()

    def _write_pending(self) -> None:
        with self._cond:
            generation, text, retired = self._pending  # type: ignore[misc]
        spare = None
        try:
            tmp = self.path.with_name(self.path.name + ".tmp")
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(text)
            os.replace(tmp, self.path)
            # the snapshot is in place: what the older generations said, it says
            for old in self._generations():
                if old < generation:
                    self.generation_path(old).unlink(missing_ok=True)
            self.journal_path.unlink(missing_ok=True)
            spare = (generation + 1, self._create(generation + 1))
        except OSError as exc:
            self._warn(exc)
        finally:
            if retired is not None:
                os.close(retired)
            with self._cond:
                self._pending = None
                if spare is not None:
                    self._spare = spare
                self._cond.notify_all()

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

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is pending (waiting at most `timeout_s` for the writer), then close the journals."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=timeout_s)
        with self._cond:
            for fd in (self._journal, self._spare[1] if self._spare else None):
                if fd is not None:
                    os.close(fd)
            self._journal, self._spare = None, None
