"""Whether a process is still running, by its pid (no child of ours needed)."""

from __future__ import annotations

import os
from pathlib import Path


def pid_exists(pid) -> bool:
    """True while ``pid`` is in the process table, a zombie (exited, unreaped) included. A
    process of another user counts (we may not signal it, but it is there)."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def pid_alive(pid) -> bool:
    """True while ``pid`` names a running process: in the table (`pid_exists`) and not a zombie."""
    if not pid_exists(pid):
        return False
    try:  # the state follows the command name, which may hold spaces and parentheses
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True
