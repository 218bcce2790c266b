"""Scenario files: a complete, validated description of one mission.

A scenario is TOML (docs/reference/scenario.md). `load_scenario` turns it into frozen
dataclasses and rejects anything it does not understand: every error names the file, the field,
the line where it can be found, what was found and what was expected. Which keys each table
accepts and requires comes from `autopower.model.schema`, which the reference page is rendered from.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from autopower.errors import ScenarioError
from autopower.model import schema
from autopower.model.control_plane import ControlPlaneSpec
from autopower.model.dag import Flow, find_cycle
from autopower.model.dvfs import parse_levels
from autopower.model.network import connected_parts
from autopower.model.scenario import (
    ACCOUNTING_MODES,
    TOPOLOGIES,
    Chain,
    ComponentSpec,
    LinkSpec,
    NetworkSpec,
    Platform,
    Radio,
    ReferenceRow,
    Robot,
    Scenario,
    Stage,
)
from autopower.model.variants import check_chain_variants, parse_variants

IMPORT_PATH = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")


INPUT_KEYS = schema.required("chains[].stages[].inputs[]")  # a DAG input is exactly { from, bytes }
MAX_SCENARIO_BYTES = 64 * 2**20  # a 2,000-robot fleet is well under 1 MB
MAX_INTEGER = 2**53  # beyond this a float loses integers, and nothing physical is that large
MAX_MESSAGE_BYTES = 2**30  # one message of a gigabyte is already far past any radio here
KEEP_CHOICES = ("all", "latest")  # a chain's `keep`: what a node cut off from its sink holds of its results
MAX_NESTING = 100  # real scenarios nest 4 levels; TOML parsers recurse per level (brackets in strings count too)


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped with AutoPower (usable instead of a path)."""
    folder = resources.files("autopower.scenarios")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def resolve_scenario_path(name_or_path: str | Path) -> tuple[str, str]:
    """Return (display path, TOML text) for a built-in name or a file path."""
    text_name = str(name_or_path)
    path = Path(text_name)
    try:
        exists, is_file = path.exists(), path.is_file()
    except OSError:  # e.g. a name longer than the file system allows
        exists = is_file = False
    if path.suffix == ".toml" or exists or "/" in text_name:
        if not is_file:
            raise ScenarioError(
                f"{text_name}: no such scenario file. Give a path to a .toml file or one of the "
                f"built-in names: {', '.join(builtin_scenarios())}"
            )
        return str(path), _read_text(path, text_name)
    resource = resources.files("autopower.scenarios") / f"{text_name}.toml"
    if not _NAME.fullmatch(text_name) or not resource.is_file():
        raise ScenarioError(
            f"{text_name!r} is neither a scenario file nor a built-in scenario; built-in: "
            f"{', '.join(builtin_scenarios())}"
        )
    return f"<built-in {text_name}>", resource.read_text(encoding="utf-8")


_NAME = re.compile(r"[A-Za-z0-9_.-]{1,100}")


def _linked(scenario: Scenario, topologies: Iterable[str]) -> Callable[[str, str], bool]:
    """Whether two nodes have a link in any of `topologies`, by the rules of `Scenario.link_layout`.

    A clique links every pair of its nodes, so a pair is looked up by membership: a fleet's
    N^2/2 robot-robot pairs are never built.
    """
    singles: set[frozenset[str]] = set()
    cliques: list[frozenset[str]] = []
    for topology in topologies:
        links, groups = scenario.link_layout(topology)
        singles.update(frozenset((link.a, link.b)) for link in links)
        cliques.extend(frozenset(clique.nodes) for clique in groups)
    return lambda a, b: frozenset((a, b)) in singles or any({a, b} <= nodes for nodes in cliques)


def _read_text(path: Path, shown: str) -> str:
    """The file's text; a clear error for one that is unreadable, huge or not UTF-8."""
    try:
        if path.stat().st_size > MAX_SCENARIO_BYTES:
            raise ScenarioError(f"{shown}: larger than {MAX_SCENARIO_BYTES // 2**20} MB; not a scenario file")
        raw = path.read_bytes()
    except OSError as exc:
        raise ScenarioError(f"{shown}: cannot read it ({exc.strerror or exc}); check the path and permissions") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ScenarioError(f"{shown}:{line}: not UTF-8 text (byte {exc.start}); save the file as UTF-8") from None


def load_toml(text: str, where: str) -> dict:
    """Parse TOML text; errors (syntax, nesting too deep for a scenario) as one ScenarioError."""
    depth, deepest = 0, 0
    for char in text:  # brackets also count inside strings: an over-estimate, never an under-one
        if char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth = max(0, depth - 1)
    if deepest > MAX_NESTING:
        raise ScenarioError(f"{where}: nested {deepest} levels deep (at most {MAX_NESTING}); not a scenario file")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{where}: not valid TOML: {exc}. Fix the syntax at that position.") from None
    except RecursionError:
        raise ScenarioError(f"{where}: nested too deep; not a scenario file") from None
    except ValueError as exc:  # e.g. an integer literal of thousands of digits
        raise ScenarioError(f"{where}: not a usable TOML value: {exc}") from None


def apply_latency_profile(scenario: Scenario, path: str | Path, platform: str) -> Scenario:
    """`scenario` with the latencies of a profile file written by `autopower profile` on `platform`."""
    where, text = resolve_scenario_path(path)
    data = load_toml(text, where)
    measured = data.get("latency_s")
    if not isinstance(measured, dict) or not measured:
        raise ScenarioError(f"{where}: no [latency_s] table; write one with `autopower profile --out FILE`")
    return scenario.with_latencies(measured, platform, where)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario by built-in name (``paper-fig7``) or path."""
    where, text = resolve_scenario_path(name_or_path)
    return parse_scenario(text, where)


def parse_scenario(text: str, where: str = "<string>") -> Scenario:
    data = load_toml(text, where)
    return ScenarioParser(data, text, where).scenario()


class ScenarioParser:
    """Walks the TOML tree; every accessor knows its dotted path for error messages."""

    def __init__(self, data: dict, text: str, where: str):
        self.data = data
        self.lines = text.splitlines()
        self.where = where
        # [network] loss entries as (a, b, dotted key path), in file order: whether each names a link
        # is checked once the scenario is built (`check_lossy_links`)
        self.loss_entries: list[tuple[str, str, str]] = []

    # ---- error reporting -------------------------------------------------------------------
    def fail(self, path: str, problem: str, expected: str, line_of: str | None = None) -> ScenarioError:
        line = self._line_of(line_of or path)  # line_of: a coarser path when the field is inline
        at = f"{self.where}:{line}" if line else self.where
        if len(problem) > 200:  # a whole mangled table in one line helps nobody
            problem = problem[:200] + " …"
        return ScenarioError(f"{at}: {path}: {problem}; expected {expected}")

    def _line_of(self, path: str) -> int | None:
        """Best-effort line of a dotted path like ``chains[2].period_s`` (tomllib keeps none)."""
        parts = re.findall(r"([^.\[\]]+)(?:\[(\d+)\])?", path)
        line = 0
        for i, (key, index) in enumerate(parts):
            header = ".".join(k for k, _ in parts[: i + 1])
            quoted = ".".join(f'"{k}"' if not re.fullmatch(r"[A-Za-z0-9_-]+", k) else k for k, _ in parts[: i + 1])
            if index:
                found = self._nth_line(rf"^\s*\[\[\s*{re.escape(header)}\s*\]\]", int(index), line)
            else:
                loose = r"\s*\.\s*".join(rf'"?{re.escape(k)}"?' for k, _ in parts[: i + 1])  # quoted or bare keys
                found = self._nth_line(rf"^\s*\[\s*({re.escape(header)}|{re.escape(quoted)}|{loose})\s*\]", 0, line)
                if found is None:
                    found = self._nth_line(rf'^\s*"?{re.escape(key)}"?\s*=', 0, line)
            if found is not None:
                line = found
        return line + 1 if line or parts else None

    def _nth_line(self, pattern: str, n: int, start: int) -> int | None:
        rx = re.compile(pattern)
        count = 0
        for i in range(start, len(self.lines)):
            if rx.search(self.lines[i]):
                if count == n:
                    return i
                count += 1
        return None

    # ---- typed accessors ------------------------------------------------------------------
    def table(self, obj: Any, path: str, allowed: Iterable[str], required: Iterable[str] = ()) -> dict:
        if not isinstance(obj, dict):
            raise self.fail(path, f"found {type(obj).__name__} {obj!r}", "a table")
        allowed = set(allowed)
        for key in obj:
            if key not in allowed:
                raise self.fail(
                    f"{path}.{key}" if path else key,
                    "unknown key",
                    f"one of {', '.join(sorted(allowed))} (check the spelling)",
                )
        missing = [key for key in required if key not in obj]
        if missing:
            names = ", ".join(repr(k) for k in missing)
            raise self.fail(path or "(top level)", f"missing required key{'s' if len(missing) > 1 else ''} {names}",
                            "every one of them (see docs/reference/scenario.md)")
        return obj

    def section(self, obj: Any, path: str, schema_path: str) -> dict:
        """`table` with the keys `autopower.model.schema` lists for `schema_path` (e.g. ``robots[]``)."""
        return self.table(obj, path, schema.allowed(schema_path), schema.required(schema_path))

    def number(self, obj: dict, key: str, path: str, *, minimum: float | None = None,
               positive: bool = False, default: float | None = None) -> float:
        if key not in obj:
            if default is not None:
                return default
            raise self.fail(path, f"missing required key {key!r}", f"{key} = <number>")
        value = obj[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(f"{path}.{key}", f"found {value!r}", "a number")
        if isinstance(value, int) and abs(value) > MAX_INTEGER:
            raise self.fail(f"{path}.{key}", f"found {value}", f"a number of magnitude at most {MAX_INTEGER}")
        if not math.isfinite(value):
            raise self.fail(f"{path}.{key}", f"found {value}", "a finite number")
        if positive and not value > 0:
            raise self.fail(f"{path}.{key}", f"found {value}", "a number > 0")
        if minimum is not None and value < minimum:
            raise self.fail(f"{path}.{key}", f"found {value}", f"a number >= {minimum}")
        return float(value)

    def string(self, obj: dict, key: str, path: str, *, choices: Iterable[str] | None = None,
               default: str | None = None) -> str:
        if key not in obj:
            if default is not None:
                return default
            raise self.fail(path, f"missing required key {key!r}", f"{key} = \"...\"")
        value = obj[key]
        if not isinstance(value, str) or not value:
            raise self.fail(f"{path}.{key}", f"found {value!r}", "a non-empty string")
        if choices is not None and value not in choices:
            raise self.fail(f"{path}.{key}", f"found {value!r}", f"one of {', '.join(choices)}")
        return value

    def strings(self, obj: dict, key: str, path: str, *, choices: Iterable[str] | None = None,
                default: tuple[str, ...] = ()) -> tuple[str, ...]:
        value = obj.get(key, list(default))
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise self.fail(f"{path}.{key}", f"found {value!r}", "a list of strings")
        if choices is not None:
            choices = list(choices)
            for v in value:
                if v not in choices:
                    raise self.fail(f"{path}.{key}", f"found {v!r}", f"one of {', '.join(choices)}")
        return tuple(value)

    # ---- sections --------------------------------------------------------------------------
    def scenario(self) -> Scenario:
        top = self.section(self.data, "", "")
        head = self.section(top["scenario"], "scenario", "scenario")
        platforms = self.platforms(top["platforms"])
        radios = self.radios(top["radios"])
        base = self.section(top["basestation"], "basestation", "basestation")
        limit_radios = base.get("limit_radios", False)
        if not isinstance(limit_radios, bool):
            raise self.fail("basestation.limit_radios", f"found {limit_radios!r}", "true or false")
        base_name = self.string(base, "name", "basestation")
        base_platform = self.string(base, "platform", "basestation", choices=list(platforms))
        robots = self.robots(top["robots"], platforms, base_name)
        nodes = [r.name for r in robots] + [base_name]
        network = self.network(top["network"], radios, robots, base_name)
        components = self.components(top["components"], platforms)
        chains = self.chains(top["chains"], components, robots, nodes, base_name)
        self.check_dag_choices(chains, components, platforms)
        rows = self.reference_rows(top.get("reference_rows", []), radios, chains, nodes, network)
        migration = self.migration(top.get("migration", {}), components)
        scenario = Scenario(
            name=self.string(head, "name", "scenario"),
            description=str(head.get("description", "")),
            source_path=self.where,
            accounting=self.string(head, "accounting", "scenario", choices=ACCOUNTING_MODES, default="paper"),
            lifetime_rounding_s=self.number(head, "lifetime_rounding_s", "scenario", minimum=0.0, default=0.8),
            platforms=platforms,
            radios=radios,
            robots=robots,
            basestation=base_name,
            basestation_platform=base_platform,
            network_spec=network,
            components=components,
            chains=chains,
            reference_rows=rows,
            migration=migration,
            basestation_radio_limit=limit_radios,
            quality_weight=self.quality_weight(top.get("mission", {})),
            hold_budget_bytes=self.hold_budget(top.get("delivery", {})),
            control_plane=self.control_plane(top.get("control_plane", {})),
        )
        self.check_lossy_links(scenario)
        self.check_routable(scenario)
        return scenario

    def check_dag_choices(self, chains, components, platforms) -> None:
        """DAG flows together with quality variants or DVFS levels are not planned yet: the planner's
        variant and level search (`planner.plan_choices`) does not charge flows, so refuse the file
        rather than plan it wrong."""
        fan_in = next((i for i, c in enumerate(chains) if c.inputs), None)
        if fan_in is None:
            return
        choices = sorted([f"components.{n}.variants" for n, c in components.items() if c.variants]
                         + [f"platforms.{n}.levels" for n, p in platforms.items() if p.levels])
        if choices:
            raise self.fail(f"chains[{fan_in}].inputs", f"DAG inputs together with {', '.join(choices)}",
                            "either DAG inputs or quality variants/DVFS levels in one scenario (both at once is "
                            "not supported yet)")

    def quality_weight(self, obj: Any) -> float:
        mission = self.section(obj, "mission", "mission")
        weight = self.number(mission, "quality_weight", "mission", minimum=0.0, default=0.0)
        if weight > 1:
            raise self.fail("mission.quality_weight", f"found {weight}", "a weight in [0, 1] (0: lifetime only)")
        return weight

    def hold_budget(self, obj: Any) -> int:
        delivery = self.section(obj, "delivery", "delivery")
        return int(self.number(delivery, "hold_budget_mb", "delivery", positive=True, default=64.0) * 2**20)

    def control_plane(self, obj: Any) -> ControlPlaneSpec:
        section = self.section(obj, "control_plane", "control_plane")
        enabled = section.get("enabled", False)
        if not isinstance(enabled, bool):
            raise self.fail("control_plane.enabled", f"found {enabled!r}", "true or false")
        numbers = {key: self.number(section, key, "control_plane", positive=True)
                   for key in ("status_period_s", "heartbeat_s", "max_detection_s") if key in section}
        if "lease_s" in section:  # the runtime's floor: below it a busy machine looks like a dead peer
            numbers["lease_s"] = self.number(section, "lease_s", "control_plane", minimum=0.1)
        sizes = {key: int(self.number(section, key, "control_plane", minimum=0.0))
                 for key in ("status_bytes", "status_change_bytes", "peer_status_bytes", "keep_alive_bytes",
                             "packet_overhead_bytes",
                             "ack_bytes", "relayed_extra_bytes") if key in section}
        if "keep_alives_per_lease" in section:
            sizes["keep_alives_per_lease"] = int(self.number(section, "keep_alives_per_lease", "control_plane",
                                                             minimum=1.0))
        if "max_detection_s" in numbers and "lease_s" not in numbers:
            try:
                numbers["lease_s"] = ControlPlaneSpec.lease_for(numbers["max_detection_s"])
            except ScenarioError as exc:
                raise self.fail("control_plane.max_detection_s", str(exc).removeprefix("control_plane: "),
                                "a requirement of at least 0.5 s") from None
        if "max_detection_s" in numbers and "heartbeat_s" not in numbers:
            numbers["heartbeat_s"] = ControlPlaneSpec.heartbeat_for(
                numbers["max_detection_s"], numbers.get("status_period_s", ControlPlaneSpec.status_period_s))
        try:
            return ControlPlaneSpec(enabled=enabled, **numbers, **sizes)
        except ScenarioError as exc:
            raise self.fail("control_plane", str(exc).removeprefix("control_plane: "),
                            "a lease no longer than max_detection_s and a heartbeat no longer than half of it") from None

    def platforms(self, obj: Any) -> dict[str, Platform]:
        obj = self.table(obj, "platforms", obj.keys() if isinstance(obj, dict) else [])
        if not obj:
            raise self.fail("platforms", "no platform defined", "at least one [platforms.NAME] table")
        out = {}
        for name, spec in obj.items():
            path = f"platforms.{name}"
            spec = self.section(spec, path, "platforms.<platform>")
            mains = spec.get("mains", False)
            if not isinstance(mains, bool):
                raise self.fail(f"{path}.mains", f"found {mains!r}", "true or false")
            idle = self.number(spec, "idle_w", path, minimum=0.0, default=0.0 if mains else None)
            busy = self.number(spec, "busy_w", path, minimum=0.0, default=idle if mains else None)
            if busy < idle:
                raise self.fail(f"{path}.busy_w", f"busy_w {busy} < idle_w {idle}", "busy_w >= idle_w")
            slowdown = self.number(spec, "slowdown", path, positive=True) if "slowdown" in spec else None
            out[name] = Platform(name=name, idle_w=idle, busy_w=busy, mains=mains, slowdown=slowdown,
                                 levels=parse_levels(self, spec["levels"], f"{path}.levels") if "levels" in spec else ())
        return out

    def radios(self, obj: Any) -> dict[str, Radio]:
        obj = self.table(obj, "radios", obj.keys() if isinstance(obj, dict) else [])
        out = {}
        for name, spec in obj.items():
            path = f"radios.{name}"
            spec = self.section(spec, path, "radios.<medium>")
            radio = Radio(
                name=name,
                kbps=self.number(spec, "kbps", path, positive=True),
                sleep_w=self.number(spec, "sleep_w", path, minimum=0.0),
                send_w=self.number(spec, "send_w", path, minimum=0.0),
                receive_w=self.number(spec, "receive_w", path, minimum=0.0),
            )
            # The planner's MILP relies on active power >= sleep power (a radio never saves
            # energy by transmitting); every real radio satisfies it.
            for key in ("send_w", "receive_w"):
                if getattr(radio, key) < radio.sleep_w:
                    raise self.fail(f"{path}.{key}", f"{key} {getattr(radio, key)} < sleep_w {radio.sleep_w}",
                                    f"{key} >= sleep_w")
            out[name] = radio
        if not out:
            raise self.fail("radios", "no radio defined", "at least one [radios.NAME] table")
        return out

    def robots(self, obj: Any, platforms: dict[str, Platform], base: str) -> tuple[Robot, ...]:
        if not isinstance(obj, list) or not obj:
            raise self.fail("robots", f"found {obj!r}", "one or more [[robots]] tables")
        out, seen = [], set()
        for i, spec in enumerate(obj):
            path = f"robots[{i}]"
            spec = self.section(spec, path, "robots[]")
            name = self.string(spec, "name", path)
            if name in seen or name == base:
                raise self.fail(f"{path}.name", f"duplicate node name {name!r}", "unique robot names")
            seen.add(name)
            platform = self.string(spec, "platform", path, choices=list(platforms))
            if platforms[platform].mains:
                raise self.fail(f"{path}.platform", f"{platform!r} is mains-powered",
                                "a battery platform for a robot")
            out.append(Robot(
                name=name,
                platform=platform,
                energy_j=self.number(spec, "energy_j", path, positive=True),
                sensors=frozenset(self.strings(spec, "sensors", path)),
            ))
        return tuple(out)

    def network(self, obj: Any, radios: dict[str, Radio], robots: tuple[Robot, ...], base: str) -> NetworkSpec:
        path = "network"
        obj = self.section(obj, path, "network")
        topology = self.string(obj, "topology", path, choices=TOPOLOGIES)
        names = [r.name for r in robots]
        relay = obj.get("relay")
        if relay is not None:
            relay = self.string(obj, "relay", path, choices=names)
        media = list(radios)
        lr = self.strings(obj, "laptop_robot_media", path, choices=media)
        rr = self.strings(obj, "robot_robot_media", path, choices=media)
        links: list[LinkSpec] = []
        if topology == "explicit":
            raw = obj.get("links")
            if not isinstance(raw, list) or not raw:
                raise self.fail("network.links", f"found {raw!r}", "[[network.links]] tables for an explicit topology")
            nodes = names + [base]
            for i, spec in enumerate(raw):
                lpath = f"network.links[{i}]"
                spec = self.section(spec, lpath, "network.links[]")
                a = self.string(spec, "a", lpath, choices=nodes)
                b = self.string(spec, "b", lpath, choices=nodes)
                if a == b:
                    raise self.fail(lpath, f"link from {a} to itself", "two different nodes")
                link_media = self.strings(spec, "media", lpath, choices=media)
                if not link_media:
                    raise self.fail(f"{lpath}.media", "empty list", "at least one medium")
                group = self.string(spec, "group", lpath, default=f"{a}-{b}")
                links.append(LinkSpec(a=a, b=b, media=link_media, group=group))
            by_group: dict[str, tuple[str, ...]] = {}
            for i, link in enumerate(links):
                if by_group.setdefault(link.group, link.media) != link.media:
                    raise self.fail(f"network.links[{i}].media", f"group {link.group!r} has different media lists",
                                    "the same candidate media on every link of a group")
        else:
            for key, value in (("laptop_robot_media", lr), ("robot_robot_media", rr)):
                if not value:
                    raise self.fail(path, f"missing {key}", f"{key} = [\"802.11a\", ...] for topology {topology}")
        analyze = self.strings(obj, "analyze_topologies", path, choices=TOPOLOGIES, default=(topology,))
        if "explicit" in analyze and topology != "explicit":
            raise self.fail("network.analyze_topologies", "explicit listed without links", "named topologies only")
        loss = self.link_losses(obj.get("loss", {}), names + [base])
        return NetworkSpec(topology=topology, relay=relay, laptop_robot_media=lr, robot_robot_media=rr,
                           links=tuple(links), analyze_topologies=analyze, loss=loss)

    def link_losses(self, raw: Any, nodes: list[str]) -> dict[frozenset[str], float]:
        """``[network] loss = { "A-B" = 0.1, ... }``: each listed link's share of packets lost.

        Every entry is kept in `loss_entries`; `check_lossy_links` checks it names a link.
        """
        path = "network.loss"
        example = f'loss = {{ "{nodes[-1]}-{nodes[0]}" = 0.1 }}'
        if not isinstance(raw, dict):
            raise self.fail(path, f"found {raw!r}", f"a table of links and their loss, e.g. {example}")
        out: dict[frozenset[str], float] = {}
        seen: set[frozenset[str]] = set()
        for key, value in raw.items():
            kpath = f'{path}."{key}"'
            pairs = [(key[:i], key[i + 1:]) for i, char in enumerate(key)
                     if char == "-" and key[:i] in nodes and key[i + 1:] in nodes]
            if len(pairs) != 1:
                unknown = [p for p in key.split("-") if p not in nodes] if key.count("-") == 1 else []
                problem = (f"unknown node{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))}" if unknown
                           else f"{key!r} does not name two nodes" if not pairs
                           else f"{key!r} can be read as {' or '.join('-'.join(p) for p in pairs)}")
                raise self.fail(kpath, problem, f'"A-B" with A and B two of the nodes {", ".join(nodes)}, e.g. '
                                               f"{example}", line_of=path)
            a, b = pairs[0]
            if a == b:
                raise self.fail(kpath, f"a link from {a} to itself", "two different nodes", line_of=path)
            pair = frozenset((a, b))
            if pair in seen:
                raise self.fail(kpath, f"the link {a}-{b} is listed twice", "one entry per link (A-B and B-A are "
                                                                            "the same link)", line_of=path)
            seen.add(pair)
            self.loss_entries.append((a, b, kpath))
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise self.fail(kpath, f"found {value!r}", "a number, the share of packets lost: "
                                                           "0 <= loss < 1 (0.1 for 10 %)", line_of=path)
            if not 0 <= value < 1:
                raise self.fail(kpath, f"found {value}", "0 <= loss < 1, a share of packets (0.1 for 10 %; a "
                                                         "link that loses everything is cut, not lossy)",
                                line_of=path)
            if value > 0:
                out[pair] = float(value)
        return out

    def components(self, obj: Any, platforms: dict[str, Platform]) -> dict[str, ComponentSpec]:
        obj = self.table(obj, "components", obj.keys() if isinstance(obj, dict) else [])
        out = {}
        for name, spec in obj.items():
            path = f"components.{name}"
            spec = self.section(spec, path, "components.<component>")
            lat = self.table(spec["latency_s"], f"{path}.latency_s", platforms)
            missing = [p for p in platforms if p not in lat]
            if missing:
                raise self.fail(f"{path}.latency_s", f"no latency for platform(s) {', '.join(missing)}",
                                "a latency for every platform (it may run anywhere)")
            plugin = {key: self.import_path(spec, key, path) for key in ("implementation", "source") if key in spec}
            if len(plugin) == 1:
                have, lacking = next(iter(plugin)), ({"implementation", "source"} - set(plugin)).pop()
                raise self.fail(f"{path}.{have}", f"{have} without {lacking}",
                                'both implementation = "pkg.mod:Component" and source = "pkg.mod:Source"')
            out[name] = ComponentSpec(
                name=name, latency_s={p: self.number(lat, p, f"{path}.latency_s", positive=True) for p in lat},
                implementation=plugin.get("implementation"), source=plugin.get("source"),
                defined_at={key: self.position(f"{path}.{key}") for key in ("latency_s", *plugin)},
                variants=parse_variants(self, spec["variants"], f"{path}.variants", platforms) if "variants" in spec else (),
            )
        return out

    def import_path(self, obj: dict, key: str, path: str) -> str:
        """A "package.module:Class" string (imported later, by `autopower.chains.plugins`)."""
        value = self.string(obj, key, path)
        if not IMPORT_PATH.fullmatch(value):
            raise self.fail(f"{path}.{key}", f"found {value!r}", '"package.module:ClassName"')
        return value

    def position(self, path: str) -> str:
        line = self._line_of(path)
        return f"{self.where}:{line}" if line else self.where

    def chains(self, obj: Any, components: dict[str, ComponentSpec], robots: tuple[Robot, ...],
               nodes: list[str], base: str) -> tuple[Chain, ...]:
        if not isinstance(obj, list):
            raise self.fail("chains", f"found {obj!r}", "[[chains]] tables")
        robot_by_name = {r.name: r for r in robots}
        out, stage_names = [], set()
        self.flow_specs: list[tuple[str, str, Any]] = []  # (stage path, stage name, raw inputs), for dag_flows
        for i, spec in enumerate(obj):
            path = f"chains[{i}]"
            spec = self.section(spec, path, "chains[]")
            name = self.string(spec, "name", path)
            sourced = "source" in spec or not self.first_stage_has_inputs(spec)
            if not sourced:  # a DAG chain fed only by other stages (autopower.model.dag): lives at its sink
                for key in ("requires",):
                    if key in spec:
                        raise self.fail(f"{path}.{key}", "set on a chain without a source", "no requires")
                sink = self.string(spec, "sink", path)
                spec = {**spec, "source": base if sink == "operator" else sink, "sink": sink}
                if spec["source"] not in nodes:
                    raise self.fail(f"{path}.sink", f"found {sink!r}", f"\"operator\" or a node: {', '.join(nodes)}")
                if isinstance(spec["message_bytes"], list):  # no sensor hop: source -> stage 0 carries 0 B
                    spec["message_bytes"] = [0, *spec["message_bytes"]]
            source = self.string(spec, "source", path, choices=list(robot_by_name) + ([] if sourced else [base]))
            sink = self.string(spec, "sink", path, default="source")
            sink = {"source": source, "operator": base}.get(sink, sink)
            if sink not in nodes:
                raise self.fail(f"{path}.sink", f"found {sink!r}",
                                f"\"source\", \"operator\" or a node: {', '.join(nodes)}")
            period = self.number(spec, "period_s", path, positive=True)
            stages = self.stages(spec, path, name, components, nodes)
            for st in stages:
                if st.name in stage_names:
                    raise self.fail(path, f"duplicate stage/chain name {st.name!r}", "unique names")
                stage_names.add(st.name)
            sizes = spec["message_bytes"]
            if (not isinstance(sizes, list) or len(sizes) != len(stages) + 1
                    or not all(isinstance(s, int) and not isinstance(s, bool) and 0 <= s <= MAX_MESSAGE_BYTES
                               for s in sizes)):
                raise self.fail(f"{path}.message_bytes", f"found {sizes[1:] if not sourced else sizes!r}",
                                f"{len(stages) + int(sourced)} non-negative integers of at most {MAX_MESSAGE_BYTES} "
                                + ("(source->first stage, ..., last stage->sink)" if sourced
                                   else "(first stage->second, ..., last stage->sink; a chain without a source has no sensor hop)"))
            requires = frozenset(self.strings(spec, "requires", path))
            lacking = requires - (robot_by_name[source].sensors if sourced else frozenset())
            if lacking:
                raise self.fail(f"{path}.requires", f"source robot {source} lacks {', '.join(sorted(lacking))}",
                                f"a source with those sensors (it has {', '.join(sorted(robot_by_name[source].sensors)) or 'none'})")
            out.append(Chain(name=name, source=source, sink=sink, period_s=period, stages=stages,
                             message_bytes=tuple(sizes), requires=requires, sourced=sourced,
                             min_quality=self.number(spec, "min_quality", path, minimum=0.0, default=0.0),
                             keep=self.string(spec, "keep", path, choices=KEEP_CHOICES, default="all")))
        check_chain_variants(self, out, components)
        return self.dag_flows(tuple(out))

    # ---- DAG flows (autopower.model.dag) -------------------------------------------------------
    @staticmethod
    def first_stage_has_inputs(spec: dict) -> bool:
        if "stages" in spec:
            raw = spec["stages"]
            return isinstance(raw, list) and bool(raw) and isinstance(raw[0], dict) and "inputs" in raw[0]
        return "inputs" in spec

    def dag_flows(self, chains: tuple[Chain, ...]) -> tuple[Chain, ...]:
        """Resolve every stage's `inputs` into flows; reject unknown or same-chain producers, a
        producer listed twice, a period mismatch (the join is by step) and cycles."""
        by_stage = {s.name: c for c in chains for s in c.stages}
        flows: dict[str, list[Flow]] = {c.name: [] for c in chains}
        where: dict[tuple[str, str], tuple[str, str]] = {}
        for spath, consumer, raw in self.flow_specs:
            ipath = f"{spath}.inputs"
            # the line of `inputs = [...]`, or of `stages = [...]` when it sits inside a stage's inline table
            line_path = f"{spath.split('.stages[')[0]}.stages" if ".stages[" in spath else ipath

            def bad(field: str, problem: str, expected: str) -> ScenarioError:
                return self.fail(field, problem, expected, line_path)  # noqa: B023 (called in this iteration)

            if not isinstance(raw, list) or not raw:
                raise bad(ipath, f"found {raw!r}", 'a non-empty list of { from = "STAGE", bytes = N }')
            seen = set()
            for k, item in enumerate(raw):
                fpath = f"{ipath}[{k}]"
                if not isinstance(item, dict) or set(item) != set(INPUT_KEYS):
                    keys = sorted(item) if isinstance(item, dict) else None
                    missing = sorted(set(INPUT_KEYS) - set(keys or ()))
                    raise bad(fpath, f"missing required key {missing[0]!r}" if keys is not None and missing
                              else f"found {item!r}", '{ from = "STAGE", bytes = N } and nothing else')
                producer = item["from"]
                if not isinstance(producer, str) or producer not in by_stage:
                    raise bad(f"{fpath}.from", f"unknown stage {producer!r}",
                              f"a stage of another chain: {', '.join(by_stage)}")
                home, chain = by_stage[producer], by_stage[consumer]
                if chain.sourced or chain.stages[0].name != consumer:
                    raise bad(ipath, f"inputs on {consumer!r}, a stage its own chain feeds",
                              "inputs only on the first stage of a chain without a source (the runtime joins "
                              "stages fed by inputs alone; put the fan-in stage first in a chain of its own)")
                if home is chain:
                    raise bad(f"{fpath}.from", f"{producer!r} is in the same chain as {consumer!r}",
                              "a stage of another chain (within a chain each stage already feeds the next)")
                if producer in seen:
                    raise bad(f"{fpath}.from", f"{producer!r} listed twice", "each input once")
                seen.add(producer)
                if home.period_s != chain.period_s:
                    raise bad(f"{fpath}.from", f"{producer} runs every {home.period_s:g} s, {consumer} every "
                              f"{chain.period_s:g} s", "the same period_s (inputs are joined step by step)")
                n_bytes = item["bytes"]
                if isinstance(n_bytes, bool) or not isinstance(n_bytes, int) or not 0 <= n_bytes <= MAX_MESSAGE_BYTES:
                    raise bad(f"{fpath}.bytes", f"found {n_bytes!r}", f"a non-negative integer of at most {MAX_MESSAGE_BYTES}")
                flows[chain.name].append(Flow(producer=producer, consumer=consumer, n_bytes=n_bytes))
                where[(producer, consumer)] = (f"{fpath}.from", line_path)
        out = tuple(dataclasses.replace(c, inputs=tuple(flows[c.name])) if flows[c.name] else c for c in chains)
        cycle = find_cycle(out)
        if cycle is not None:
            first = next(((a, b) for a, b in zip(cycle, cycle[1:], strict=False) if (a, b) in where), None)
            field, line_path = where[first] if first else ("chains", None)
            raise self.fail(field, f"cycle {' > '.join(cycle)}", "an acyclic graph of stages (remove one of these inputs)",
                            line_path)
        return out

    def stages(self, spec: dict, path: str, chain_name: str, components: dict, nodes: list[str]) -> tuple[Stage, ...]:
        if ("component" in spec) == ("stages" in spec):
            raise self.fail(path, "needs exactly one of 'component' or 'stages'",
                            "component = \"Loc\" for a one-stage chain, or stages = [{name, component}, ...]")
        if "component" in spec:
            raw = [{"name": chain_name, "component": spec["component"],
                    **{k: spec[k] for k in ("pin", "hosts", "inputs") if k in spec}}]
        else:
            raw = spec["stages"]
            if not isinstance(raw, list) or not raw:
                raise self.fail(f"{path}.stages", f"found {raw!r}", "a non-empty list of {name, component}")
            for key in ("pin", "hosts", "inputs"):
                if key in spec:
                    raise self.fail(f"{path}.{key}", "set on a multi-stage chain", f"{key} inside each stage")
        out = []
        for j, st in enumerate(raw):
            spath = f"{path}.stages[{j}]" if "stages" in spec else path
            st = self.section(st, spath, "chains[].stages[]")
            if "inputs" in st:
                self.flow_specs.append((spath, self.string(st, "name", spath), st["inputs"]))
            pin = st.get("pin")
            if pin is not None:
                pin = self.string(st, "pin", spath, choices=nodes)
            hosts = tuple(self.strings(st, "hosts", spath, choices=nodes)) if "hosts" in st else None
            out.append(Stage(name=self.string(st, "name", spath),
                             component=self.string(st, "component", spath, choices=list(components)),
                             pin=pin, hosts=hosts))
        return tuple(out)

    def reference_rows(self, obj: Any, radios: dict, chains: tuple[Chain, ...], nodes: list[str],
                       network: NetworkSpec) -> tuple[ReferenceRow, ...]:
        if not isinstance(obj, list):
            raise self.fail("reference_rows", f"found {obj!r}", "[[reference_rows]] tables")
        stages = [s.name for c in chains for s in c.stages]
        groups = {link.group: link.media for link in network.links}
        out = []
        for i, spec in enumerate(obj):
            path = f"reference_rows[{i}]"
            spec = self.section(spec, path, "reference_rows[]")
            alloc = self.table(spec["allocation"], f"{path}.allocation", stages, stages)
            for stage, host in alloc.items():
                if host not in nodes:
                    raise self.fail(f"{path}.allocation.{stage}", f"found {host!r}", f"one of {', '.join(nodes)}")
            topology = self.string(spec, "topology", path, choices=TOPOLOGIES)
            media: dict[str, str] = {}
            if topology == "explicit":
                # an explicit row names each link group's medium: media = { uplink = "gsm", ... }
                if network.topology != "explicit":
                    raise self.fail(f"{path}.topology", "explicit without [[network.links]]",
                                    "fully-connected or relay, or an explicit [network]")
                for key in ("laptop_robot", "robot_robot"):
                    if key in spec:
                        raise self.fail(f"{path}.{key}", "set on an explicit row", "media = { GROUP = MEDIUM, ... }")
                media = dict(self.table(spec.get("media", {}), f"{path}.media", groups))
                for group, medium in media.items():
                    if medium not in groups[group]:
                        raise self.fail(f"{path}.media.{group}", f"found {medium!r}",
                                        f"one of the group's media: {', '.join(groups[group])}")
                media = {g: media.get(g, m[0]) for g, m in groups.items()}
                lr = rr = None
            else:
                if "media" in spec:
                    raise self.fail(f"{path}.media", "set on a named topology", "laptop_robot and robot_robot")
                for key in ("laptop_robot", "robot_robot"):
                    if key not in spec:
                        raise self.fail(path, f"missing required key {key!r}", f"{key} = \"<medium>\"")
                lr = self.string(spec, "laptop_robot", path, choices=list(radios))
                rr = self.string(spec, "robot_robot", path, choices=list(radios))
            out.append(ReferenceRow(
                topology=topology, laptop_robot=lr, robot_robot=rr, media=media,
                allocation=dict(alloc),
                paper_lifetime_s=(self.number(spec, "paper_lifetime_s", path, positive=True)
                                  if "paper_lifetime_s" in spec else None),
            ))
        return tuple(out)

    def migration(self, obj: Any, components: Mapping[str, ComponentSpec]) -> dict[str, Any]:
        """What moving a component costs: downtime, CPU, and state bytes per component type."""
        obj = self.section(obj, "migration", "migration")
        out: dict[str, Any] = {k: self.number(obj, k, "migration", minimum=0.0) for k in obj if k != "state_bytes"}
        if "state_bytes" in obj:
            sizes = self.table(obj["state_bytes"], "migration.state_bytes", components)
            out["state_bytes"] = {k: self.number(sizes, k, "migration.state_bytes", minimum=0.0) for k in sizes}
        return out

    def check_lossy_links(self, scenario: Scenario) -> None:
        """Every `[network] loss` entry must name a link of a topology the scenario plans (its own
        or one `analyze_topologies` lists); which nodes a topology links is `Scenario.link_layout`'s."""
        if not self.loss_entries:
            return
        spec = scenario.network_spec
        linked = _linked(scenario, dict.fromkeys((spec.topology, *spec.analyze_topologies)))
        for a, b, kpath in self.loss_entries:
            if not linked(a, b):
                raise self.fail(kpath, f"{a} and {b} have no link in the topologies planned", "a pair of nodes "
                                "the topology links (`analyze_topologies` included)", line_of="network.loss")

    def check_routable(self, scenario: Scenario) -> None:
        """Every chain must be able to reach its sink on every topology `analyze` explores.

        The named topologies connect every node by construction (each robot to the base station
        or to the relay, which reaches it); only explicit links can leave a node unreachable.
        Linear in the links listed: a fleet's N^2/2 implied robot-robot links are never built.
        """
        spec = scenario.network_spec
        if "explicit" not in (spec.topology, *spec.analyze_topologies):
            return
        part = connected_parts(scenario.node_names(), ((link.a, link.b) for link in spec.links))
        for chain in scenario.chains:
            if part[chain.source] != part[chain.sink]:
                raise ScenarioError(
                    f"{self.where}: chain {chain.name}: its sink {chain.sink} cannot be reached from "
                    f"{chain.source} on the explicit topology; add a link or change the sink"
                )
