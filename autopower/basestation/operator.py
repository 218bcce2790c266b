"""The operator's side of the base station: send a command, get a reply (and a snapshot).

Used by `autopower up` (readiness, the live table, the summary) and by `autopower chain ...`,
`autopower migrate ...`, `autopower status`. It is a plain Zenoh query on ``base/operator``.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

from autopower.errors import AutoPowerError, ProtocolError
from autopower.protocol import Keys, OperatorReply, SnapshotRequest, decode, encode
from autopower.protocol.keys import check_name
from autopower.runtime.bus import Bus, ZenohBus, ZenohSettings
from autopower.runtime.pids import pid_alive

SESSION_FILE = "session.json"
TEAMS_DIR = "teams"  # one directory per running team: its session file and control socket
TLS_DIR = "tls"  # one directory per team started on this machine: the keys `up` made for it


def state_dir() -> Path:
    """Where `autopower up` records how to reach its team (AUTOPOWER_STATE_DIR overrides)."""
    env = os.environ.get("AUTOPOWER_STATE_DIR")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state")) / "autopower"


def private_dir(path: Path) -> Path:
    """`path` (and missing parents) as a directory only this user can enter: 0700 whatever the umask."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    if path.stat().st_uid != os.getuid():
        raise AutoPowerError(f"{path} belongs to another user; set AUTOPOWER_STATE_DIR to a directory of your own")
    os.chmod(path, 0o700)
    return path


def team_dir(team: str) -> Path:
    """The directory of one team's state files (created 0700)."""
    check_name(team, "team")
    root = private_dir(state_dir())
    return private_dir(private_dir(root / TEAMS_DIR) / team)


def write_session(info: dict) -> Path:
    """Record how to reach `info["team"]` (its own directory; the file 0600)."""
    path = team_dir(info["team"]) / SESSION_FILE
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(info, indent=2))
    os.chmod(tmp, 0o600)
    tmp.replace(path)
    return path


def running_sessions(clean_stale: bool = True) -> dict[str, dict]:
    """Team name -> session of every team whose `up` is still alive; a dead team's files are removed."""
    root = state_dir() / TEAMS_DIR
    out: dict[str, dict] = {}
    try:
        folders = sorted(p for p in root.iterdir() if p.is_dir())
    except FileNotFoundError:
        return out
    for folder in folders:
        try:
            session = json.loads((folder / SESSION_FILE).read_text())
        except FileNotFoundError:
            session = None
        except (json.JSONDecodeError, OSError, UnicodeDecodeError):
            session = {}
        if isinstance(session, dict) and session.get("team") == folder.name and pid_alive(session.get("pid")):
            out[folder.name] = session
        elif clean_stale and session is not None:  # its `up` died without cleaning up (SIGKILL, a crash)
            remove_team_files(folder.name)
    return out


def read_session(team: str | None = None, *, remote_hint: bool = True) -> dict:
    """The session of `team`, or of the only running team; a clear error naming the running ones.

    ``remote_hint``: the error also says how to reach a base station elsewhere (--connect), which
    commands that only work on a team `up` started here (`fault`) must not suggest.
    """
    sessions = running_sessions()
    names = ", ".join(sessions) or "none"
    if team is not None:
        if team not in sessions:
            raise AutoPowerError(f"no running team {team!r} on this machine (running: {names}); start it with "
                                 "`autopower up`" + (", or pass --connect ENDPOINT to reach a base station elsewhere"
                                                     if remote_hint else ""))
        return sessions[team]
    if not sessions:
        raise AutoPowerError(f"no running team found (nothing in {state_dir() / TEAMS_DIR}); start one with "
                             "`autopower up`" + (", or pass --connect ENDPOINT --team TEAM" if remote_hint else ""))
    if len(sessions) > 1:
        raise AutoPowerError(f"{len(sessions)} teams are running ({names}); choose one with --team NAME")
    return next(iter(sessions.values()))


# What a team's base station keeps in the team's folder across its restarts (`basestation.process`:
# lock, incarnation; `agent.sink_store`: the operator sink's ledgers; `agent.held_store`: results it
# holds for a robot's sink out of reach), with the temporary files of their atomic rewrites
# (the lock last: removed while this process still holds it, nothing of the team is left then)
BASESTATION_STATE_FILES = ("sinks.json", "sinks.json.tmp", "basestation.held", "basestation.held.tmp",
                           "basestation.json", "basestation.json.tmp", "basestation.lock")


def basestation_state_paths(folder: Path) -> list[Path]:
    """The base station's files in its state folder, its held results' journal generations included."""
    return [folder / name for name in BASESTATION_STATE_FILES] + sorted(folder.glob("basestation.held.journal.*"))


def remove_team_files(team: str) -> None:
    """Remove one team's session file, control socket and directory; nothing of any other team."""
    folder = state_dir() / TEAMS_DIR / check_name(team, "team")
    for path in [folder / SESSION_FILE, folder / SESSION_FILE.replace(".json", ".tmp"), folder / "control.sock",
                 *basestation_state_paths(folder)]:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
    # the agents' resume files (autopower.agent.resume.AGENTS_DIR): their mission ended with the team
    shutil.rmtree(folder / "agents", ignore_errors=True)
    # the keys `up` made for the team (autopower.launch.identities): of no use once it is gone, and
    # a dead `up` (SIGKILL) could not remove them itself
    shutil.rmtree(state_dir() / TLS_DIR / check_name(team, "team"), ignore_errors=True)
    try:
        folder.rmdir()
    except OSError:  # not empty (something we did not put there) or already gone
        pass


def clear_session(team: str, pid: int | None = None) -> None:
    """Remove `team`'s files if they are this process's (`pid`, default ours)."""
    path = state_dir() / TEAMS_DIR / check_name(team, "team") / SESSION_FILE
    try:
        owner = json.loads(path.read_text()).get("pid")
    except (FileNotFoundError, json.JSONDecodeError, OSError):
        owner = None
    if owner in (None, pid or os.getpid()):
        remove_team_files(team)


class OperatorClient:
    """A Zenoh session that talks to one team's base station (a context manager)."""

    def __init__(self, team: str, connect: tuple[str, ...] = (), bus: Bus | None = None,
                 settings: ZenohSettings | None = None):
        """``settings`` replaces the plain session to ``connect`` (e.g. mutual TLS as the operator)."""
        self.keys = Keys(team)
        self._owns = bus is None
        if bus is None:
            bus = ZenohBus(settings if settings is not None else ZenohSettings(connect=tuple(connect)))
        self.bus = bus

    def __enter__(self) -> "OperatorClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._owns:
            self.bus.close()

    def request(self, command, timeout_s: float = 5.0, *, held_s: float = 0.0) -> OperatorReply:
        """Send one command; retries until the base station answers or ``timeout_s`` passes.
        ``held_s``: how long the base station may hold the command before it answers (each try
        waits that much longer)."""
        deadline = time.monotonic() + timeout_s
        payload = encode(command)
        while True:
            left = deadline - time.monotonic()
            replies = self.bus.query(self.keys.operator, payload, timeout_s=max(0.2, min(2.0 + held_s, left)))
            for raw in replies:
                try:
                    return decode(raw, OperatorReply)
                except ProtocolError as exc:
                    raise AutoPowerError(f"the base station answered garbage: {exc}") from exc
            if time.monotonic() >= deadline:
                raise AutoPowerError(f"no base station answered on {self.keys.operator} within {timeout_s:g} s; "
                                     "is `autopower up` (or `autopower basestation`) running for this team?")
            time.sleep(0.05)

    def snapshot(self, timeout_s: float = 5.0, *, until_ready_s: float = 0.0) -> dict:
        """The team's snapshot; with ``until_ready_s``, once the team is ready or that many seconds
        have passed (`SnapshotRequest`)."""
        return self.request(SnapshotRequest(until_ready_s=until_ready_s), max(timeout_s, until_ready_s + 2.0),
                            held_s=until_ready_s).snapshot
