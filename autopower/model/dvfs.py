"""Dynamic voltage and frequency scaling (the paper's future work).

A platform may declare frequency levels, each with its own idle and busy power and a latency
factor (how much longer every component run takes than at the platform's nominal latencies).
At level l a robot hosting stages of nominal utilisation u runs at utilisation f_l * u (at most
100 %) and draws idle_l + (busy_l - idle_l) * f_l * u on its CPU. The radios do not change.

A robot's level changes only its own CPU power and CPU limit, so for a fixed placement the best
level of every robot is independent of the others: the cheapest level at which it still fits
(`best_levels`). The planners use that; the MILP models the choice with one binary per level.

A platform without levels is the one-level special case: idle_w, busy_w and factor 1. When no
level is chosen for a robot (evaluating a given allocation) its platform's nominal figures apply.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from autopower.errors import ScenarioError
from autopower.model.scenario import Scenario

UTILISATION_LIMIT = 1.0 + 1e-9


@dataclass(frozen=True, kw_only=True)
class FrequencyLevel:
    name: str
    idle_w: float
    busy_w: float
    latency_factor: float  # >= 1 for a level slower than the nominal latencies
    mhz: float | None = None  # documentation: where the level comes from
    core_v: float | None = None


def has_levels(scenario: Scenario) -> bool:
    return any(scenario.platform_of(r.name).levels for r in scenario.robots)


def levels_of(scenario: Scenario, robot: str) -> tuple[FrequencyLevel, ...]:
    return tuple(scenario.platform_of(robot).levels)


def level_named(scenario: Scenario, robot: str, name: str) -> FrequencyLevel:
    for level in levels_of(scenario, robot):
        if level.name == name:
            return level
    names = [lv.name for lv in levels_of(scenario, robot)]
    raise ScenarioError(f"frequency level {name!r} for {robot}: "
                        + (f"its platform has {', '.join(names)}" if names else "its platform declares no levels"))


def derived_platform(platform: str, level: str) -> str:
    return f"{platform}@{level}"


def apply_levels(scenario: Scenario, levels: Mapping[str, str] | None) -> Scenario:
    """The scenario with each named robot on a derived platform "<platform>@<level>": the level's
    idle and busy power, and every component's latency on it scaled by the level's factor."""
    if not levels:
        return scenario
    platforms = dict(scenario.platforms)
    components = dict(scenario.components)
    robots = []
    for robot in scenario.robots:
        if robot.name not in levels:
            robots.append(robot)
            continue
        level = level_named(scenario, robot.name, levels[robot.name])
        name = derived_platform(robot.platform, level.name)
        if name not in platforms:
            base = scenario.platforms[robot.platform]
            platforms[name] = dataclasses.replace(base, name=name, idle_w=level.idle_w, busy_w=level.busy_w, levels=())
            for cname, spec in list(components.items()):
                if robot.platform in spec.latency_s:
                    components[cname] = dataclasses.replace(
                        spec, latency_s={**spec.latency_s, name: spec.latency_s[robot.platform] * level.latency_factor})
        robots.append(dataclasses.replace(robot, platform=name))
    return dataclasses.replace(scenario, platforms=platforms, components=components, robots=tuple(robots))


def level_table(scenario: Scenario, robots) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[list[str]]]:
    """Per robot and level (R, L), padded with the last level: idle_w, extra_w (busy - idle), factor;
    and the level names. Robots without levels get their platform's figures as one level."""
    rows = []
    for robot in robots:
        platform = scenario.platform_of(robot)
        levels = platform.levels or (FrequencyLevel(name="", idle_w=platform.idle_w, busy_w=platform.busy_w,
                                                    latency_factor=1.0),)
        rows.append(levels)
    width = max((len(r) for r in rows), default=1)
    pad = [list(r) + [r[-1]] * (width - len(r)) for r in rows]
    idle = np.array([[lv.idle_w for lv in r] for r in pad]).reshape(len(rows), width)
    extra = np.array([[lv.busy_w - lv.idle_w for lv in r] for r in pad]).reshape(len(rows), width)
    factor = np.array([[lv.latency_factor for lv in r] for r in pad]).reshape(len(rows), width)
    return idle, extra, factor, [[lv.name for lv in r] for r in pad]


def best_cpu_power(idle: np.ndarray, extra: np.ndarray, factor: np.ndarray, u: np.ndarray):
    """For nominal utilisations u (K, R): the least CPU power over the levels at which each robot
    fits (K, R; inf where none fits) and the index of that level (K, R)."""
    scaled = u[..., None] * factor  # (K, R, L)
    power = idle + extra * scaled
    power = np.where(scaled <= UTILISATION_LIMIT, power, np.inf)
    pick = power.argmin(axis=-1)
    return np.take_along_axis(power, pick[..., None], axis=-1)[..., 0], pick


def cpu_at_best_levels(space, parts: dict) -> tuple[np.ndarray, np.ndarray]:
    """For a `model.energy.LoadSpace` breakdown: CPU watts (K, R) with every robot at its cheapest
    fitting level (inf where none fits), and the level index chosen (K, R)."""
    idle, extra, factor, _ = level_table(space.scenario, space.robots)
    return best_cpu_power(idle, extra, factor, parts["cpu_u"])


def best_levels(scenario: Scenario, utilisation: Mapping[str, float]) -> dict[str, str]:
    """The cheapest level at which each robot with levels fits, for its nominal CPU utilisation
    (robots that fit at none keep their fastest level: the plan is infeasible anyway)."""
    out = {}
    for robot, u in utilisation.items():
        levels = [lv for lv in scenario.platforms[scenario.robot(robot).platform].levels] \
            if robot != scenario.basestation else []
        if not levels:
            continue
        fits = [lv for lv in levels if u * lv.latency_factor <= UTILISATION_LIMIT]
        pick = min(fits, key=lambda lv: lv.idle_w + (lv.busy_w - lv.idle_w) * lv.latency_factor * u) if fits \
            else min(levels, key=lambda lv: lv.latency_factor)
        out[robot] = pick.name
    return out


# ---- loading (called by autopower.model.loading) --------------------------------------------------
def parse_levels(parser, obj: Any, path: str) -> tuple[FrequencyLevel, ...]:
    """`[platforms.NAME.levels.LEVEL]` tables; errors name file:line:field."""
    obj = parser.table(obj, path, obj.keys() if isinstance(obj, dict) else [])
    out = []
    for name, spec in obj.items():
        lpath = f"{path}.{name}"
        spec = parser.section(spec, lpath, "platforms.<platform>.levels.<level>")
        idle = parser.number(spec, "idle_w", lpath, minimum=0.0)
        busy = parser.number(spec, "busy_w", lpath, minimum=0.0)
        if busy < idle:
            raise parser.fail(f"{lpath}.busy_w", f"busy_w {busy} < idle_w {idle}", "busy_w >= idle_w")
        factor = parser.number(spec, "latency_factor", lpath, positive=True)
        if factor < 1:  # the platform's latencies are its fastest level's: a level only slows down
            raise parser.fail(f"{lpath}.latency_factor", f"found {factor}",
                              "a factor >= 1 (the platform's latency_s are measured at its fastest level)")
        if "@" in name:
            raise parser.fail(lpath, f"level name {name!r} contains '@'", "a name without '@'")
        out.append(FrequencyLevel(
            name=name, idle_w=idle, busy_w=busy, latency_factor=factor,
            mhz=parser.number(spec, "mhz", lpath, positive=True) if "mhz" in spec else None,
            core_v=parser.number(spec, "core_v", lpath, positive=True) if "core_v" in spec else None))
    if not out:
        raise parser.fail(path, "no level declared", "at least one [..levels.NAME] table, or no levels key")
    return tuple(out)
