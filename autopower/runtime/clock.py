"""Clocks: mission (virtual) time with a speed factor, and a manual clock for tests.

Virtual time ``t`` (seconds since the mission's start) is what the energy model sees: periods,
idle power, lifetimes. Wall time is what the machine sees: when to wake up. A `VirtualClock`
maps one to the other with ``wall = epoch_unix + t / speed``. Every process of a team builds
its clock from the same `MissionInfo` (epoch and speed), so on one machine they agree exactly;
on real robots the wall clocks must be NTP-synchronised.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    speed: float

    def now(self) -> float:
        """Virtual seconds since the mission's start."""
        ...

    def wall(self) -> float:
        """Wall time (unix seconds) now."""
        ...

    def wall_at(self, t_virtual: float) -> float:
        """Wall time (unix seconds) at which virtual time reaches ``t_virtual``."""
        ...


class VirtualClock:
    """Mission time running ``speed`` times faster than the wall clock from ``epoch_unix``."""

    def __init__(self, epoch_unix: float, speed: float = 1.0, *, wall_fn=time.time):
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.epoch_unix = float(epoch_unix)
        self.speed = float(speed)
        self._wall = wall_fn

    def now(self) -> float:
        return (self._wall() - self.epoch_unix) * self.speed

    def wall(self) -> float:
        return self._wall()

    def wall_at(self, t_virtual: float) -> float:
        return self.epoch_unix + t_virtual / self.speed

    def __repr__(self) -> str:
        return f"VirtualClock(epoch_unix={self.epoch_unix:.3f}, speed={self.speed:g})"


class WallClock(VirtualClock):
    """Mission time equal to wall time since ``epoch_unix`` (speed 1)."""

    def __init__(self, epoch_unix: float | None = None):
        super().__init__(time.time() if epoch_unix is None else epoch_unix, 1.0)


class ManualClock:
    """A clock that only moves when a test says so (deterministic unit tests)."""

    def __init__(self, t: float = 0.0, speed: float = 1.0, epoch_unix: float = 1_000_000.0):
        self.t = float(t)
        self.speed = float(speed)
        self.epoch_unix = epoch_unix

    def now(self) -> float:
        return self.t

    def wall(self) -> float:
        return self.epoch_unix + self.t / self.speed

    def wall_at(self, t_virtual: float) -> float:
        return self.epoch_unix + t_virtual / self.speed

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError("a clock does not go back")
        self.t += dt
        return self.t

    def set(self, t: float) -> float:
        if t < self.t:
            raise ValueError("a clock does not go back")
        self.t = float(t)
        return self.t
