"""Where a process's event loop is stuck, said while it is stuck.

A robot's loop that stops turning misses source periods, statuses and silence checks; its log
then says *that* it was away ("stopped for 1.4 s") but not *where*. A `LoopWatch` thread looks
every `check_s` while the loop works, every `idle_check_s` while it waits for an event (each look
wakes the process: ten a second were a fifth of an agent's CPU at rest); when the loop has been
working (not waiting for an event) for `after_s`, it logs the loop thread's innermost frames once
for that stall, at most `idle_check_s` + `check_s` after it began. Its own lateness is evidence too: a check
that itself ran `after_s` late means the whole process was not running (the machine, or a C call
holding the GIL), not one blocked call.

Rule: the loop calls `working()` when it takes an event or a timer and `waiting()` before it blocks
on its queue; only time spent working counts, so an idle loop at rest is never reported.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
import traceback

log = logging.getLogger(__name__)

FRAMES_SHOWN = 6  # innermost frames: the blocked call and what called it


class LoopWatch:
    def __init__(self, name: str, *, after_s: float = 0.5, check_s: float = 0.1, idle_check_s: float | None = None,
                 clock=time.monotonic, loop_thread: threading.Thread | None = None):
        self.name = name
        self.after_s = after_s
        self.check_s = check_s
        self.idle_check_s = after_s if idle_check_s is None else idle_check_s
        self._clock = clock
        self._loop_ident = (loop_thread or threading.current_thread()).ident
        self._working_since: float | None = None
        self._reported_since: float | None = None  # the stall already reported
        self._stop = threading.Event()
        self.stalls = 0  # stalls reported (a loop stuck working for after_s)
        self._thread = threading.Thread(target=self._run, name=f"loop-watch {name}", daemon=True)
        self._thread.start()

    def working(self) -> None:
        if self._working_since is None:
            self._working_since = self._clock()

    def waiting(self) -> None:
        self._working_since = None

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _run(self) -> None:
        while True:
            before = self._clock()
            step = self.check_s if self._working_since is not None else self.idle_check_s
            if self._stop.wait(step):
                return
            now = self._clock()
            # only the wait counts: a report's own logging may wait for the disk like the loop did
            late = now - before - step
            if late >= self.after_s:
                log.warning("%s: this process did not run for %.1f s (the machine, or a call holding the GIL)",
                            self.name, late)
            self.check(now)

    def check(self, now: float) -> str | None:
        """Report the loop's stack if it has worked for `after_s` without waiting; the report, or None."""
        since = self._working_since
        if since is None or now - since < self.after_s or self._reported_since == since:
            return None
        self._reported_since = since
        self.stalls += 1
        where = self.where()
        log.warning("%s: the loop has been busy for %.1f s without taking an event; it is in: %s",
                    self.name, now - since, where)
        return where

    def where(self) -> str:
        """The loop thread's innermost frames, innermost last: 'file:line function <- ...'."""
        frame = sys._current_frames().get(self._loop_ident)
        if frame is None:
            return "(the loop thread has ended)"
        frames = traceback.extract_stack(frame)[-FRAMES_SHOWN:]
        return " <- ".join(f"{f.filename.rsplit('/', 2)[-1] if '/' in f.filename else f.filename}:{f.lineno} "
                           f"{f.name}" for f in reversed(frames))
