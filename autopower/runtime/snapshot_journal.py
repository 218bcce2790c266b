"""A file kept as a snapshot plus the records appended since, written so that an event loop never
waits for the file system's metadata.

Rule: the event loop never creates, truncates, renames or unlinks a file. Those calls wait for the
file system's journal, and under a burst of writes by anything else on the machine they took 1-2 s
each (two robots' loops stopped together, missing a second of source periods). Appending to a file
that is already open is a copy into the page cache and does not wait.

So the state is a snapshot (``<path>``, replaced atomically: written to ``<path>.tmp`` and renamed
over it) and journal generations (``<path>.journal.<g>``) that the loop only appends to. A
snapshot names the generation that follows it: the caller writes that number into the snapshot's
content (`snapshot` hands it over), and a load applies that generation and every later one on top
of the snapshot. With ``background=True`` a writer thread of its own writes each snapshot, then
removes the older generations and creates the next one empty, ready for the loop's next snapshot.
While the writer is behind, a snapshot is skipped (`skipped` counts them; the caller's next one
is newer) and the loop goes on appending: nothing appended is ever lost. A kill at any instant
leaves either the old snapshot and every generation from the one it names, or the new one and its
own. Without the thread (``background=False``, the simulator) the same steps run in the caller.

A snapshot may name a side file (``<path>.side.<name>``): content that changes far less often than
the snapshot (a robot's plan, which lists the team, beside its battery, which changes at every
status). It is written once, before the first snapshot that names it is put in place, and removed
once a snapshot naming another one is: a kill leaves every side file a snapshot on disk names.

Never raises for a failing disk: the first error goes to ``on_error`` (the caller says what a
restart would lose) and the operation reports failure.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)


class SnapshotJournal:
    def __init__(self, path: str | Path, *, background: bool = False,
                 on_error: Callable[[OSError], None] | None = None, supersedes: tuple[Path, ...] = ()):
        """``supersedes``: files of an older layout the first snapshot in place makes obsolete."""
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self._on_error = on_error
        self._supersedes = supersedes
        self._journal: int | None = None  # the open generation the loop appends to
        self._generation = 0
        self._failed = False
        self._cond = threading.Condition()
        self._spare: tuple[int, int] | None = None  # (generation, fd): created ahead by the writer
        # (generation, content, fd it retires, its side file: (name, content) or None)
        self._pending: tuple[int, bytes, int | None, tuple[str, bytes] | None] | None = None
        self._sides: set[str] | None = None  # the side files on disk (listed once, then kept like generations)
        self._closing = False
        # The generations on disk, listed once, then kept as this journal creates and removes them
        # (only its own process writes them): a snapshot does not list a folder that other
        # processes' stores share (n agents of a localhost team, n robots of a simulated one).
        self._on_disk: set[int] | None = None
        self._on_disk_lock = threading.Lock()
        self.skipped = 0  # snapshots not written because the one before was still being written
        self._thread: threading.Thread | None = None
        if background:
            self._thread = threading.Thread(target=self._run, name=f"snapshot {self.path.name}", daemon=True)
            self._thread.start()

    # ---- reading -------------------------------------------------------------------------------
    @property
    def current_journal(self) -> Path:
        """The generation appends go to now."""
        return self.generation_path(self._generation)

    def generation_path(self, generation: int) -> Path:
        return self.path.with_name(f"{self.path.name}.journal.{generation}")

    def generations(self) -> list[int]:
        """The journal generations on disk, oldest first."""
        prefix = self.path.name + ".journal."
        try:
            names = [p.name for p in self.path.parent.iterdir()]
        except OSError:
            return []
        return sorted(int(n[len(prefix):]) for n in names if n.startswith(prefix) and n[len(prefix):].isdigit())

    def _known_generations(self) -> list[int]:
        """`generations` as this journal keeps them (the folder listed the first time only)."""
        with self._on_disk_lock:
            if self._on_disk is None:
                self._on_disk = set(self.generations())
            return sorted(self._on_disk)

    def _known(self, generation: int, on_disk: bool) -> None:
        with self._on_disk_lock:
            if self._on_disk is not None:
                (self._on_disk.add if on_disk else self._on_disk.discard)(generation)

    def read_snapshot(self) -> bytes | None:
        """The snapshot's content (None if there is none); OSError if it cannot be read."""
        try:
            return self.path.read_bytes()
        except FileNotFoundError:
            return None

    def journals_since(self, generation: int) -> list[bytes]:
        """What was appended to generation ``generation`` and every later one, in order (one item each)."""
        out = []
        for g in self.generations():
            if g >= generation:
                try:
                    out.append(self.generation_path(g).read_bytes())
                except OSError:
                    continue  # removed by a writer meanwhile: a newer snapshot holds it
        return out

    # ---- writing -------------------------------------------------------------------------------
    def side_path(self, name: str) -> Path:
        return self.path.with_name(f"{self.path.name}.side.{name}")

    def snapshot(self, content: Callable[[int], bytes], *, wait_s: float = 0.0,
                 side: tuple[str, bytes] | None = None) -> bool:
        """Replace the snapshot with ``content(g)``, where ``g`` is the generation it must name (the
        appends from now on go there); False if skipped (the writer is behind) or the disk failed.

        ``wait_s``: how long to wait for a snapshot still being written, instead of skipping.
        ``side``: (name, content) of the side file the snapshot names (written only if not on disk yet).
        """
        if wait_s > 0 and self._thread is not None:
            self.written(wait_s)  # only this caller hands snapshots over: none can start meanwhile
        with self._cond:
            if self._pending is not None or self._closing:
                self.skipped += 1
                return False
            if self._spare is not None:
                spare, self._spare = self._spare, None
            else:  # no thread, or the writer could not create the next generation: here
                spare = self._open_next()
                if spare is None:
                    return False
            retired = self._journal
            self._generation, self._journal = spare
            self._pending = (self._generation, content(self._generation), retired, side)
            self._cond.notify_all()
        if self._thread is None:
            self._write_pending()
        return True

    def append(self, record: bytes) -> bool:
        """One ``write`` to the current generation; False if it failed.

        Before this process's first snapshot the record goes to a new generation after every one on
        disk: a restarted process appends before it snapshots, and the snapshot its predecessor left
        reads every generation from the one it names on (`journals_since`), so nothing appended is
        lost to a second crash."""
        if self._journal is None:
            with self._cond:
                if self._thread is not None:  # the writer creates the next generation as it starts
                    self._cond.wait_for(lambda: self._spare is not None or self._closing, timeout=1.0)
                if self._journal is None and not self._closing:
                    # the spare, or one made here: either way after every generation on disk, and
                    # before the one the first snapshot opens (journals are read in order)
                    opened, self._spare = (self._spare or self._open_next()), None
                    if opened is not None:
                        self._generation, self._journal = opened
            if self._journal is None:
                return False
        try:
            _write_all(self._journal, record)
            return True
        except OSError as exc:
            self._error(exc)
            return False

    def written(self, timeout_s: float) -> bool:
        """Wait until no snapshot is being written (at most `timeout_s`); whether none is."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending is None, timeout=timeout_s)

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

    # ---- the writer ----------------------------------------------------------------------------
    def _open_next(self) -> tuple[int, int] | None:
        """A new generation after every one on disk and the current one, created here.

        Rule: a generation number is chosen and its file created in one step under the lock, and the
        file is created exclusively. The loop's first append and the writer thread may both open the
        next generation (the loop when the writer is slow to make its spare): with a number chosen
        by each and the file truncated on open, the second would erase what the first appended."""
        try:
            self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            with self._on_disk_lock:
                if self._on_disk is None:
                    self._on_disk = set(self.generations())
                generation = max([*self._on_disk, self._generation], default=0) + 1
                while True:
                    try:
                        fd = os.open(self.generation_path(generation),
                                     os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o600)
                    except FileExistsError:  # made since the folder was listed: it is someone's
                        self._on_disk.add(generation)
                        generation += 1
                        continue
                    self._on_disk.add(generation)
                    return generation, fd
        except OSError as exc:
            self._error(exc)
            return None

    def _run(self) -> None:
        spare = self._open_next()  # ahead of the first snapshot, which must not create it on the loop
        with self._cond:
            self._spare = spare
            self._cond.notify_all()
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                if self._pending is None:
                    return
            self._write_pending()

    def _write_pending(self) -> None:
        with self._cond:
            generation, content, retired, side = self._pending  # type: ignore[misc]
        spare = None
        try:
            sides = self._known_sides()
            if side is not None and side[0] not in sides:  # before the snapshot that names it
                self._replace(self.side_path(side[0]), side[1])
                sides.add(side[0])
            self._replace(self.path, content)
            for name in sorted(sides - ({side[0]} if side is not None else set())):  # named by no snapshot now
                self.side_path(name).unlink(missing_ok=True)
                sides.discard(name)
            # the snapshot is in place: what the older generations said, it says
            for old in self._known_generations():
                if old < generation:
                    self.generation_path(old).unlink(missing_ok=True)
                    self._known(old, False)
            supersedes, self._supersedes = self._supersedes, ()
            for path in supersedes:
                path.unlink(missing_ok=True)
            spare = self._open_next()  # the next snapshot's generation (`snapshot` names it)
        except OSError as exc:
            self._error(exc)
        finally:
            if retired is not None:
                os.close(retired)
            with self._cond:
                self._pending = None
                if spare is not None:
                    self._spare = spare
                self._cond.notify_all()

    def _replace(self, path: Path, content: bytes) -> None:
        """``path`` replaced atomically by ``content`` (written to ``<snapshot>.tmp`` and renamed)."""
        fd = os.open(self._tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            _write_all(fd, content)
        finally:
            os.close(fd)
        os.replace(self._tmp, path)

    def _known_sides(self) -> set[str]:
        """The side files on disk: listed once (a crashed predecessor's included), then kept (writer only)."""
        if self._sides is None:
            prefix = f"{self.path.name}.side."
            try:
                self._sides = {p.name[len(prefix):] for p in self.path.parent.glob(prefix + "*")}
            except OSError:
                self._sides = set()
        return self._sides

    def _error(self, exc: OSError) -> None:
        if not self._failed:  # once: a full disk must not flood the log at the caller's rate
            self._failed = True
            if self._on_error is not None:
                self._on_error(exc)
            else:
                log.warning("%s not written (%s)", self.path, exc)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]
