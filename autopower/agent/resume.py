"""What a restarted agent needs to carry on where it crashed: battery, mission, source positions.

The agent writes its resume state to a file of its own (0600, in the team's state directory:
``AUTOPOWER_STATE_DIR``, which the systemd units point at ``/var/lib/autopower``) at every
status tick and after every frame a source produces, by atomic replace. A process killed with
SIGKILL loses nothing written before (the page cache outlives it), so whoever restarts the
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
    """One agent's resume state on disk (never raises: a robot runs on without it)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
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
        return state

    def save(self, state: dict) -> None:
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            self.path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(json.dumps({"version": VERSION, **state}))
            os.replace(tmp, self.path)
        except OSError as exc:
            if not self._warned:  # once: a full disk must not flood the log at the source's rate
                log.warning("resume state not written to %s (%s): a restart would reset the battery",
                            self.path, exc)
                self._warned = True

    def remove(self) -> None:
        for path in (self.path, self.path.with_name(self.path.name + ".tmp")):
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            except OSError:
                pass


def mission_key(mission) -> dict:
    """What identifies one mission (a `MissionInfo`): a restarted agent resumes only the same one."""
    return {"scenario": mission.scenario, "epoch_unix": mission.epoch_unix, "speed": mission.speed}
