"""How a team process's C allocator treats large buffers: kept for reuse, not handed back at once.

glibc serves an allocation above 128 kB (its default ``M_MMAP_THRESHOLD``) with a fresh ``mmap``
and returns it with ``munmap`` when it is freed, so every such buffer costs a page fault per 4 kB
page on first touch, every time. A live team allocates such buffers for every frame: the camera's
230 kB images (rendered, encoded, received, decoded), and numpy's temporaries in the components
(MCL's 1,000 particles x 60 beams: ~0.5 MB each, a dozen per run). glibc raises the threshold by
itself after freeing one such block, but not reliably (it depends on what was freed first):
the same MCL run can take 4.9 ms of CPU in one process and 2.9 ms in another, and encoding a
camera frame 232 us against 19 us (docs/performance.md).

`keep_large_buffers` fixes both thresholds once at start: blocks up to 16 MB come from the heap
and are reused, and up to 64 MB freed at the heap's top is kept before it is returned to the
system (a process's resident memory may stay that much above what it uses). Only glibc has
``mallopt``; elsewhere this does nothing.
"""

from __future__ import annotations

import ctypes
import logging

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 16 * 2**20  # larger blocks still get a mapping of their own
TRIM_THRESHOLD_BYTES = 64 * 2**20


def keep_large_buffers() -> bool:
    """Set the allocator's thresholds (glibc); True if they were set."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError):  # not glibc (macOS, musl without it): nothing to tune
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    done = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    if not done:
        log.debug("mallopt refused the thresholds; large buffers stay mapped one by one")
    return done
