"""A snapshot and its journals written so that the loop never waits for the file system's metadata."""

from __future__ import annotations

import os
import threading
import time

import autopower.runtime.snapshot_journal as files
from autopower.runtime.snapshot_journal import SnapshotJournal


def test_with_a_writer_the_loop_never_creates_renames_or_removes_a_file(tmp_path, monkeypatch):
    store = SnapshotJournal(tmp_path / "state", background=True)
    deadline = time.monotonic() + 5
    while not (tmp_path / "state.journal.1").exists() and time.monotonic() < deadline:
        time.sleep(0.01)  # the writer creates the first generation ahead of the first snapshot
    loop, calls = threading.current_thread(), []
    for name in ("open", "replace", "rename", "unlink"):
        real = getattr(os, name)

        def spy(*args, _real=real, _name=name, **kwargs):
            if threading.current_thread() is loop:
                calls.append(_name)
            return _real(*args, **kwargs)
        monkeypatch.setattr(files.os, name, spy)
    for n in range(3):
        assert store.snapshot(lambda generation, n=n: b"%d %d\n" % (n, generation))
        assert store.append(b"note %d\n" % n)
        assert store.written(5)
    monkeypatch.undo()
    store.close()
    assert calls == []
    # what a load sees: the last snapshot (naming generation 3) and the note appended after it
    assert (tmp_path / "state").read_bytes() == b"2 3\n"
    assert store.journals_since(3) == [b"note 2\n", b""] and store.generations() == [3, 4]  # 4: the spare


def test_a_failing_disk_is_reported_once_and_never_raises(tmp_path):
    (tmp_path / "sub").write_text("a file where the folder should be")
    errors = []
    store = SnapshotJournal(tmp_path / "sub" / "state", on_error=errors.append)
    assert not store.snapshot(lambda generation: b"x")
    assert not store.snapshot(lambda generation: b"y")
    assert not store.append(b"note")
    assert len(errors) == 1


def test_a_generation_made_since_the_folder_was_listed_is_never_truncated(tmp_path, monkeypatch):
    """The loop's first append and the writer thread may both open the next generation (the loop when
    the writer is slow): the one that comes second must take the number after, not erase the first's
    records by opening the same file again."""
    store = SnapshotJournal(tmp_path / "state")
    # its listing of the folder was taken before the other opener made generation 1
    monkeypatch.setattr(store, "generations", lambda: [])
    fd = os.open(tmp_path / "state.journal.1", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    os.write(fd, b"theirs\n")
    os.close(fd)
    assert store.append(b"mine\n")
    monkeypatch.undo()
    assert (tmp_path / "state.journal.1").read_bytes() == b"theirs\n"
    assert (tmp_path / "state.journal.2").read_bytes() == b"mine\n"
    assert oct((tmp_path / "state.journal.2").stat().st_mode & 0o777) == "0o600"
    assert store.snapshot(lambda generation: b"s %d\n" % generation)  # after both
    assert (tmp_path / "state").read_bytes() == b"s 3\n"
    store.close()
