"""The operator's side of the base station: send a command, get a reply (and a snapshot).

Used by `autopower up` (readiness, the live table, the summary) and by `autopower chain ...`,
`autopower migrate ...`, `autopower status`. It is a plain Zenoh query on ``base/operator``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

from autopower.errors import AutoPowerError, ProtocolError
from autopower.protocol import Keys, OperatorReply, SnapshotRequest, decode, encode
from autopower.runtime.bus import Bus, ZenohBus, ZenohSettings

SESSION_FILE = "session.json"


def state_dir() -> Path:
    """Where `autopower up` records how to reach the running team (AUTOPOWER_STATE_DIR overrides)."""
    env = os.environ.get("AUTOPOWER_STATE_DIR")
    if env:
        return Path(env)
    return Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state")) / "autopower"


def write_session(info: dict) -> Path:
    path = state_dir() / SESSION_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(info, indent=2))
    tmp.replace(path)
    return path


def read_session() -> dict:
    path = state_dir() / SESSION_FILE
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise AutoPowerError(f"no running team found ({path} is missing); start one with `autopower up`, "
                             "or pass --connect ENDPOINT --team TEAM") from None
    except json.JSONDecodeError as exc:
        raise AutoPowerError(f"{path} is corrupt ({exc}); remove it and pass --connect/--team") from None


def clear_session(team: str) -> None:
    path = state_dir() / SESSION_FILE
    try:
        if json.loads(path.read_text()).get("team") == team:
            path.unlink()
    except (FileNotFoundError, json.JSONDecodeError):
        pass


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

    def request(self, command, timeout_s: float = 5.0) -> OperatorReply:
        """Send one command; retries until the base station answers or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        payload = encode(command)
        while True:
            left = deadline - time.monotonic()
            replies = self.bus.query(self.keys.operator, payload, timeout_s=max(0.2, min(2.0, left)))
            for raw in replies:
                try:
                    return decode(raw, OperatorReply)
                except ProtocolError as exc:
                    raise AutoPowerError(f"the base station answered garbage: {exc}") from exc
            if time.monotonic() >= deadline:
                raise AutoPowerError(f"no base station answered on {self.keys.operator} within {timeout_s:g} s; "
                                     "is `autopower up` (or `autopower basestation`) running for this team?")
            time.sleep(0.05)

    def snapshot(self, timeout_s: float = 5.0) -> dict:
        return self.request(SnapshotRequest(), timeout_s).snapshot
