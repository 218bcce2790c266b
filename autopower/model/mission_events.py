"""Mission events for the simulator: what happens to the team, and when.

(Not to be confused with `autopower.runtime.events`, the runtime processes' event queue.)

An events file is TOML, validated as strictly as a scenario (unknown keys, wrong types, names the
scenario does not know, impossible sequences such as healing a link that is not cut: each error
names the file, the line, the field, what was found and what was expected)::

    [simulation]                    # optional
    description = "V.C: r3's 802.11a card fails after one hour"
    battery_noise = 0.0             # relative std. dev. of the battery readings the policy sees
    initially_absent = []           # robots that join later (with a robot-join event)

    [migration]                     # optional: overrides the scenario's [migration] table
    downtime_s = 0.5                # a moved stage misses ceil((downtime + transfer) / period) runs
    cpu_s = 0.05                    # busy CPU seconds on the old and on the new host
    state_bytes_default = 32768     # state shipped per moved stage ...
    state_bytes = { Loc = 32200, Blob = 1 }   # ... or per component type (measured: MCL 32197 B)

    [[events]]
    at_s = 3600                     # mission (virtual) seconds
    kind = "radio-fault"            # see KINDS
    robot = "r3"
    laptop_robot = "gsm"            # its links to the base station now use GSM ...
    robot_robot = "bluetooth"       # ... and its links to robots Bluetooth
    note = "the paper's V.C hardware fault"

Kinds and their fields: ``link-cut``/``link-heal`` (a, b), ``radio-fault`` (robot, laptop_robot
and/or robot_robot), ``radio-repair`` (robot), ``chain-disable``/``chain-enable`` (chains),
``robot-leave``/``robot-join`` (robot), ``energy-offset`` (robot, delta_j). Every event may
carry a ``note``. Events at the same time apply in file order.

`MissionEvent` values are also what the live base station hands to a policy
(`autopower.policies.TeamState.events`), so both describe the world the same way.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

from autopower.errors import ScenarioError
from autopower.model.loading import ScenarioParser
from autopower.model.scenario import Scenario

KINDS = ("link-cut", "link-heal", "radio-fault", "radio-repair", "chain-disable", "chain-enable",
         "robot-leave", "robot-join", "energy-offset")
_FIELDS = {
    "link-cut": ("a", "b"),
    "link-heal": ("a", "b"),
    "radio-fault": ("robot", "laptop_robot", "robot_robot"),
    "radio-repair": ("robot",),
    "chain-disable": ("chains",),
    "chain-enable": ("chains",),
    "robot-leave": ("robot",),
    "robot-join": ("robot",),
    "energy-offset": ("robot", "delta_j"),
}
MIGRATION_KEYS = ("downtime_s", "cpu_s", "state_bytes_default", "state_bytes")


class EventsError(ScenarioError):
    """An events file is malformed or does not fit the scenario it is used with."""


@dataclass(frozen=True, kw_only=True)
class MissionEvent:
    """One change to the team at a mission time. Fields a kind does not use stay at their default."""

    at_s: float
    kind: str
    a: str | None = None  # link ends
    b: str | None = None
    robot: str | None = None
    laptop_robot: str | None = None  # radio-fault: new medium of the robot's links to the base station
    robot_robot: str | None = None  # ... and of its links to other robots
    chains: tuple[str, ...] = ()
    delta_j: float = 0.0
    note: str = ""

    def describe(self) -> str:
        what = {
            "link-cut": lambda: f"link {self.a}–{self.b} cut",
            "link-heal": lambda: f"link {self.a}–{self.b} healed",
            "radio-fault": lambda: f"{self.robot} radio fault: " + ", ".join(
                f"{k.replace('_', '-')} links now {v}" for k, v in (("laptop_robot", self.laptop_robot),
                                                                    ("robot_robot", self.robot_robot)) if v),
            "radio-repair": lambda: f"{self.robot} radios repaired",
            "chain-disable": lambda: f"{', '.join(self.chains)} disabled",
            "chain-enable": lambda: f"{', '.join(self.chains)} enabled",
            "robot-leave": lambda: f"{self.robot} left the team",
            "robot-join": lambda: f"{self.robot} joined the team",
            "energy-offset": lambda: f"{self.robot} battery {self.delta_j:+.1f} J",
        }[self.kind]()
        return what + (f" ({self.note})" if self.note else "")

    @property
    def link(self) -> frozenset[str] | None:
        return frozenset((self.a, self.b)) if self.a is not None and self.b is not None else None


@dataclass(frozen=True, kw_only=True)
class EventScript:
    """A validated events file."""

    source_path: str
    description: str = ""
    events: tuple[MissionEvent, ...] = ()  # sorted by time; file order among equal times
    initially_absent: frozenset[str] = frozenset()
    battery_noise: float = 0.0
    migration: Mapping[str, Any] = field(default_factory=dict)  # overrides of the scenario's [migration]


NO_EVENTS = EventScript(source_path="<none>")


def builtin_events() -> list[str]:
    """Names of the shipped events files (``autopower/scenarios/events/*.events.toml``)."""
    folder = resources.files("autopower.scenarios") / "events"
    return sorted(p.name[: -len(".events.toml")] for p in folder.iterdir() if p.name.endswith(".events.toml"))


def resolve_events_path(name_or_path: str | Path) -> tuple[str, str]:
    """(display path, TOML text) for a built-in events name or a file path."""
    text_name = str(name_or_path)
    path = Path(text_name)
    if path.suffix == ".toml" or path.exists() or "/" in text_name:
        if not path.is_file():
            raise EventsError(f"{text_name}: no such events file. Give a path to a .toml file or one of the "
                              f"built-in names: {', '.join(builtin_events())}")
        return str(path), path.read_text(encoding="utf-8")
    resource = resources.files("autopower.scenarios") / "events" / f"{text_name}.events.toml"
    if not resource.is_file():
        raise EventsError(f"{text_name!r} is neither an events file nor a built-in one; built-in: "
                          f"{', '.join(builtin_events())}")
    return f"<built-in events {text_name}>", resource.read_text(encoding="utf-8")


def load_events(name_or_path: str | Path, scenario: Scenario, topology: str | None = None) -> EventScript:
    """Load an events file and check it against the scenario (and topology) it will run on."""
    where, text = resolve_events_path(name_or_path)
    return parse_events(text, scenario, where, topology=topology)


def parse_events(text: str, scenario: Scenario, where: str = "<string>", topology: str | None = None) -> EventScript:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise EventsError(f"{where}: not valid TOML: {exc}. Fix the syntax at that position.") from None
    return _EventsParser(data, text, where).script(scenario, topology)


class _EventsParser(ScenarioParser):
    def fail(self, path: str, problem: str, expected: str) -> EventsError:
        line = self._line_of(path)
        at = f"{self.where}:{line}" if line else self.where
        return EventsError(f"{at}: {path}: {problem}; expected {expected}")

    def script(self, scenario: Scenario, topology: str | None) -> EventScript:
        top = self.table(self.data, "", ["simulation", "migration", "events"])
        sim = self.table(top.get("simulation", {}), "simulation",
                         ["description", "battery_noise", "initially_absent"])
        robots = [r.name for r in scenario.robots]
        absent = frozenset(self.strings(sim, "initially_absent", "simulation", choices=robots))
        if absent and absent == set(robots):
            raise self.fail("simulation.initially_absent", "every robot is absent", "at least one robot at the start")
        noise = self.number(sim, "battery_noise", "simulation", minimum=0.0, default=0.0)
        if noise >= 0.5:
            raise self.fail("simulation.battery_noise", f"found {noise}", "a relative error < 0.5 (e.g. 0.02)")
        description = sim.get("description", "")
        if not isinstance(description, str):
            raise self.fail("simulation.description", f"found {description!r}", "a string")
        migration = self.migration_overrides(top.get("migration", {}), scenario)
        raw = top.get("events", [])
        if not isinstance(raw, list):
            raise self.fail("events", f"found {raw!r}", "[[events]] tables")
        events = [self.event(spec, i, scenario) for i, spec in enumerate(raw)]
        order = sorted(range(len(events)), key=lambda i: (events[i].at_s, i))
        self.check_sequence(events, order, scenario, topology, absent)
        return EventScript(source_path=self.where, description=description,
                           events=tuple(events[i] for i in order), initially_absent=absent,
                           battery_noise=noise, migration=migration)

    def migration_overrides(self, obj: Any, scenario: Scenario) -> dict[str, Any]:
        obj = self.table(obj, "migration", MIGRATION_KEYS)
        out: dict[str, Any] = {k: self.number(obj, k, "migration", minimum=0.0)
                               for k in obj if k != "state_bytes"}
        if "state_bytes" in obj:
            sizes = self.table(obj["state_bytes"], "migration.state_bytes", scenario.components)
            for name, value in sizes.items():
                if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                    raise self.fail(f"migration.state_bytes.{name}", f"found {value!r}", "a whole number of bytes >= 0")
            out["state_bytes"] = dict(sizes)
        return out

    def event(self, spec: Any, i: int, scenario: Scenario) -> MissionEvent:
        path = f"events[{i}]"
        if not isinstance(spec, dict):
            raise self.fail(path, f"found {spec!r}", "an [[events]] table")
        kind = self.string(spec, "kind", path, choices=KINDS)
        spec = self.table(spec, path, ("at_s", "kind", "note", *_FIELDS[kind]), ("at_s", "kind"))
        at_s = self.number(spec, "at_s", path, minimum=0.0)
        note = spec.get("note", "")
        if not isinstance(note, str):
            raise self.fail(f"{path}.note", f"found {note!r}", "a string")
        nodes = scenario.node_names()
        robots = [r.name for r in scenario.robots]
        media = list(scenario.radios)
        fields: dict[str, Any] = {}
        if kind in ("link-cut", "link-heal"):
            fields["a"] = self.string(spec, "a", path, choices=nodes)
            fields["b"] = self.string(spec, "b", path, choices=nodes)
            if fields["a"] == fields["b"]:
                raise self.fail(f"{path}.b", f"the same node as a ({fields['a']})", "the other end of a link")
        elif kind == "radio-fault":
            fields["robot"] = self.string(spec, "robot", path, choices=robots)
            for key in ("laptop_robot", "robot_robot"):
                if key in spec:
                    fields[key] = self.string(spec, key, path, choices=media)
            if not ("laptop_robot" in fields or "robot_robot" in fields):
                raise self.fail(path, "a radio fault that changes nothing",
                                "laptop_robot = \"<medium>\" and/or robot_robot = \"<medium>\"")
        elif kind in ("chain-disable", "chain-enable"):
            chains = self.strings(spec, "chains", path, choices=[c.name for c in scenario.chains])
            if not chains:
                raise self.fail(f"{path}.chains", "empty list", "one or more chain names")
            if len(set(chains)) != len(chains):
                raise self.fail(f"{path}.chains", f"found duplicates in {list(chains)}", "each chain once")
            fields["chains"] = chains
        elif kind == "energy-offset":
            fields["robot"] = self.string(spec, "robot", path, choices=robots)
            fields["delta_j"] = self.number(spec, "delta_j", path)
            if fields["delta_j"] == 0:
                raise self.fail(f"{path}.delta_j", "found 0", "a non-zero change in joules (+ charges, - drains)")
        else:  # radio-repair, robot-leave, robot-join
            fields["robot"] = self.string(spec, "robot", path, choices=robots)
        return MissionEvent(at_s=at_s, kind=kind, note=note, **fields)

    def check_sequence(self, events: list[MissionEvent], order: list[int], scenario: Scenario,
                       topology: str | None, absent: frozenset[str]) -> None:
        """Replay the events in time order and reject impossible ones (heal an intact link, ...)."""
        try:
            links = {frozenset((s.a, s.b)) for s in scenario.link_specs(topology)}
        except ScenarioError as exc:
            raise EventsError(f"{self.where}: {exc}") from None
        topo = topology or scenario.network_spec.topology
        cut: set[frozenset[str]] = set()
        faulty: set[str] = set()
        disabled: set[str] = set()
        away = set(absent)
        robots = {r.name for r in scenario.robots}
        for i in order:
            ev, path = events[i], f"events[{i}]"
            at = f"at {ev.at_s:g} s"
            if ev.kind in ("link-cut", "link-heal"):
                if ev.link not in links:
                    raise self.fail(path, f"no link {ev.a}–{ev.b} on the {topo} topology",
                                    "a link of the topology: " + ", ".join(sorted("–".join(sorted(l)) for l in links)))
                if ev.kind == "link-cut" and ev.link in cut:
                    raise self.fail(path, f"link {ev.a}–{ev.b} is already cut {at}", "a link-heal before cutting it again")
                if ev.kind == "link-heal" and ev.link not in cut:
                    raise self.fail(path, f"link {ev.a}–{ev.b} is not cut {at}", "a link-cut before it")
                (cut.add if ev.kind == "link-cut" else cut.discard)(ev.link)
            elif ev.kind == "radio-fault":
                faulty.add(ev.robot)
            elif ev.kind == "radio-repair":
                if ev.robot not in faulty:
                    raise self.fail(path, f"{ev.robot} has no radio fault {at}", "a radio-fault before it")
                faulty.discard(ev.robot)
            elif ev.kind in ("chain-disable", "chain-enable"):
                for chain in ev.chains:
                    if ev.kind == "chain-disable" and chain in disabled:
                        raise self.fail(f"{path}.chains", f"{chain} is already disabled {at}", "an enabled chain")
                    if ev.kind == "chain-enable" and chain not in disabled:
                        raise self.fail(f"{path}.chains", f"{chain} is not disabled {at}", "a disabled chain")
                    (disabled.add if ev.kind == "chain-disable" else disabled.discard)(chain)
            elif ev.kind == "robot-leave":
                if ev.robot in away:
                    raise self.fail(path, f"{ev.robot} is not in the team {at}", "a robot that is present")
                away.add(ev.robot)
                if away == robots:
                    raise self.fail(path, f"the last robot leaves {at}", "at least one robot left in the team")
            elif ev.kind == "robot-join":
                if ev.robot not in away:
                    raise self.fail(path, f"{ev.robot} is already in the team {at}",
                                    "a robot that left (or is listed in simulation.initially_absent)")
                away.discard(ev.robot)


def random_events(scenario: Scenario, seed: int, count: int = 4, *, horizon_s: float = 30_000.0,
                  topology: str | None = None, kinds: tuple[str, ...] = KINDS) -> EventScript:
    """A valid random event sequence (for property tests and benchmarks); a function of the seed."""
    import numpy as np

    rng = np.random.default_rng(seed)
    links = sorted(tuple(sorted((s.a, s.b))) for s in scenario.link_specs(topology))
    robots = [r.name for r in scenario.robots]
    chains = [c.name for c in scenario.chains]
    media = list(scenario.radios)
    cut: set[tuple[str, str]] = set()
    faulty: set[str] = set()
    disabled: set[str] = set()
    away: set[str] = set()
    times = sorted(float(round(t, 1)) for t in rng.uniform(0.0, horizon_s, count))
    out: list[MissionEvent] = []
    for t in times:
        options = []
        if "link-cut" in kinds and len(cut) < len(links):
            options.append("link-cut")
        if "link-heal" in kinds and cut:
            options.append("link-heal")
        if "radio-fault" in kinds:
            options.append("radio-fault")
        if "radio-repair" in kinds and faulty:
            options.append("radio-repair")
        if "chain-disable" in kinds and len(disabled) < len(chains):
            options.append("chain-disable")
        if "chain-enable" in kinds and disabled:
            options.append("chain-enable")
        if "robot-leave" in kinds and len(away) < len(robots) - 1:
            options.append("robot-leave")
        if "robot-join" in kinds and away:
            options.append("robot-join")
        if "energy-offset" in kinds:
            options.append("energy-offset")
        if not options:
            continue
        kind = options[int(rng.integers(len(options)))]
        if kind == "link-cut":
            a, b = [l for l in links if l not in cut][int(rng.integers(len(links) - len(cut)))]
            cut.add((a, b))
            out.append(MissionEvent(at_s=t, kind=kind, a=a, b=b))
        elif kind == "link-heal":
            a, b = sorted(cut)[int(rng.integers(len(cut)))]
            cut.discard((a, b))
            out.append(MissionEvent(at_s=t, kind=kind, a=a, b=b))
        elif kind == "radio-fault":
            robot = robots[int(rng.integers(len(robots)))]
            faulty.add(robot)
            out.append(MissionEvent(at_s=t, kind=kind, robot=robot, laptop_robot=media[int(rng.integers(len(media)))],
                                    robot_robot=media[int(rng.integers(len(media)))]))
        elif kind == "radio-repair":
            robot = sorted(faulty)[int(rng.integers(len(faulty)))]
            faulty.discard(robot)
            out.append(MissionEvent(at_s=t, kind=kind, robot=robot))
        elif kind == "chain-disable":
            chain = [c for c in chains if c not in disabled][int(rng.integers(len(chains) - len(disabled)))]
            disabled.add(chain)
            out.append(MissionEvent(at_s=t, kind=kind, chains=(chain,)))
        elif kind == "chain-enable":
            chain = sorted(disabled)[int(rng.integers(len(disabled)))]
            disabled.discard(chain)
            out.append(MissionEvent(at_s=t, kind=kind, chains=(chain,)))
        elif kind == "robot-leave":
            robot = [r for r in robots if r not in away][int(rng.integers(len(robots) - len(away)))]
            away.add(robot)
            out.append(MissionEvent(at_s=t, kind=kind, robot=robot))
        elif kind == "robot-join":
            robot = sorted(away)[int(rng.integers(len(away)))]
            away.discard(robot)
            out.append(MissionEvent(at_s=t, kind=kind, robot=robot))
        else:
            robot = robots[int(rng.integers(len(robots)))]
            out.append(MissionEvent(at_s=t, kind=kind, robot=robot,
                                    delta_j=float(round(rng.uniform(-0.15, 0.15) * scenario.robot(robot).energy_j, 1))))
    return EventScript(source_path=f"<random events seed {seed}>", events=tuple(out))
