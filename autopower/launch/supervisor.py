"""Restart policy of the launcher, the way a service manager does it (systemd's ``Restart=on-failure``).

A child that dies on its own (a signal, a non-zero status) is started again after a backoff
that doubles with every crash (`RestartPolicy.backoff_s`), while the rest of the team keeps
running. More than ``burst`` crashes within ``interval_s`` (systemd's ``StartLimitBurst`` /
``StartLimitIntervalSec``) and the supervisor gives up on that child: it is reported, never
restarted, and the others go on. Exit status 2 means bad input (a wrong option or scenario):
starting it again would fail the same way, so it is given up at once.

`Supervisor` only decides and records; the launcher does the starting (`LocalTeam.restart`).
Every crash, restart and give-up is an event (`SupervisorEvent`): the launcher shows them in
the live table and the summary, and records them in the run's Rerun recording.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import asdict, dataclass, field

BAD_CONFIGURATION = 2  # the exit status of bad input: not worth a restart


@dataclass(frozen=True)
class RestartPolicy:
    initial_backoff_s: float = 0.2
    max_backoff_s: float = 5.0
    burst: int = 5  # crashes allowed within interval_s (systemd's StartLimitBurst default)
    interval_s: float = 60.0  # (systemd's default StartLimitIntervalSec is 10 s; our backoff is slower)

    def backoff_s(self, crashes_in_window: int) -> float:
        return min(self.max_backoff_s, self.initial_backoff_s * 2 ** max(0, crashes_in_window - 1))


@dataclass(frozen=True)
class SupervisorEvent:
    t_unix: float
    node: str
    kind: str  # "crashed" | "restarted" | "gave-up"
    detail: str  # e.g. "killed by SIGKILL", "restart 2 after 0.4 s", "5 crashes in 60 s"
    exit_code: int | None = None
    restarts: int = 0  # how many times this node has been started again so far

    def line(self) -> str:
        return f"{time.strftime('%H:%M:%S', time.localtime(self.t_unix))} {self.node} {self.kind}: {self.detail}"


def describe_exit(code: int) -> str:
    if code < 0:
        import signal

        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    if code == BAD_CONFIGURATION:
        return "exited with status 2 (bad configuration)"
    return f"exited with status {code}"


@dataclass
class _Watch:
    crashes: deque = field(default_factory=deque)  # wall times of recent crashes
    restart_at: float | None = None  # monotonic time a restart is due
    restarts: int = 0
    gave_up: str | None = None  # why, once given up


class Supervisor:
    """Which children to restart and when; what happened to each (not thread-safe: one caller)."""

    def __init__(self, policy: RestartPolicy | None = None):
        self.policy = policy or RestartPolicy()
        self.events: list[SupervisorEvent] = []
        self._watch: dict[str, _Watch] = {}

    def _w(self, node: str) -> _Watch:
        return self._watch.setdefault(node, _Watch())

    def crashed(self, node: str, code: int, now: float | None = None) -> SupervisorEvent:
        """`node` exited with `code` on its own: schedule its restart, or give up on it."""
        now_unix = time.time()
        mono = time.monotonic() if now is None else now
        w = self._w(node)
        w.crashes.append(mono)
        while w.crashes and w.crashes[0] < mono - self.policy.interval_s:
            w.crashes.popleft()
        what = describe_exit(code)
        self.events.append(SupervisorEvent(now_unix, node, "crashed", what, code, w.restarts))
        if code == BAD_CONFIGURATION:
            w.gave_up = f"{what}: a restart would fail the same way"
        elif len(w.crashes) > self.policy.burst:
            w.gave_up = (f"{len(w.crashes)} crashes within {self.policy.interval_s:g} s "
                         f"(limit {self.policy.burst}); last {what}")
        if w.gave_up:
            event = SupervisorEvent(now_unix, node, "gave-up", w.gave_up, code, w.restarts)
            w.restart_at = None
        else:
            delay = self.policy.backoff_s(len(w.crashes))
            w.restart_at = mono + delay
            event = SupervisorEvent(now_unix, node, "crashed", f"{what}; restarting in {delay:.1f} s", code,
                                    w.restarts)
            self.events.pop()  # the plain "crashed" above becomes this one (says when it comes back)
        self.events.append(event)
        return event

    def due(self, now: float | None = None) -> list[str]:
        """Children whose restart is due now."""
        mono = time.monotonic() if now is None else now
        return [n for n, w in self._watch.items() if w.restart_at is not None and w.restart_at <= mono]

    def next_due(self) -> float | None:
        """The monotonic time of the next restart due (None: none scheduled)."""
        return min((w.restart_at for w in self._watch.values() if w.restart_at is not None), default=None)

    def waiting(self, node: str) -> bool:
        """A restart of `node` is scheduled (it is down on purpose, not gone)."""
        w = self._watch.get(node)
        return w is not None and w.restart_at is not None

    def restarted(self, node: str) -> SupervisorEvent:
        w = self._w(node)
        w.restart_at = None
        w.restarts += 1
        event = SupervisorEvent(time.time(), node, "restarted", f"restart {w.restarts}", None, w.restarts)
        self.events.append(event)
        return event

    def given_up(self) -> dict[str, str]:
        """Node -> why the supervisor stopped restarting it."""
        return {n: w.gave_up for n, w in self._watch.items() if w.gave_up}

    def report(self) -> dict:
        """For the status, the live table and the JSON summary."""
        return {"policy": asdict(self.policy),
                "restarts": {n: w.restarts for n, w in self._watch.items() if w.restarts},
                "crashes": sum(1 for e in self.events if e.kind == "crashed"),
                "given_up": self.given_up(),
                "events": [asdict(e) for e in self.events]}
