"""A file system whose journal is under load: the snapshot writer held inside its rename."""

from __future__ import annotations

import threading

import autopower.runtime.snapshot_journal as files


class SlowDisk:
    """Holds the writer thread inside its os.replace until `release` is set; `entered` says it is there."""

    def __init__(self, monkeypatch):
        self.entered, self.release = threading.Event(), threading.Event()
        real = files.os.replace

        def replace(src, dst):
            self.entered.set()
            self.release.wait(10)
            real(src, dst)

        monkeypatch.setattr(files.os, "replace", replace)
