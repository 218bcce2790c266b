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
