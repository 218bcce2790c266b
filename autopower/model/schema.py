"""The scenario file's schema: every table, every key, its type, whether it is required, its default.

This is the one list of what a scenario may contain. `autopower.model.loading` takes each table's
allowed and required keys from it (a key not listed here is refused as unknown), and the reference
page docs/reference/scenario.md is rendered from it (`render_markdown`), so the two cannot drift.
The loader still checks values (ranges, names that must exist, combinations); `Key.meaning` states
those rules in one line each.

Paths name tables the way the loader walks them: ``robots[]`` is each ``[[robots]]`` table,
``platforms.<platform>`` each ``[platforms.NAME]`` table.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Key:
    """One key of a table. `of`: the schema path of the table (or tables) its value holds."""

    name: str
    type: str
    meaning: str
    required: bool = False
    default: str | None = None  # shown for an optional key; None: absent means "not set"
    of: str | None = None


@dataclass(frozen=True)
class Table:
    """One table of a scenario file.

    A table with fixed keys lists them in `keys`. A table whose keys are names the file chooses
    (platforms, radios, components, latencies per platform...) has no fixed keys: `names` says what
    a key is, `value` what its value is, and `entries` the schema path of the value's table, if any.
    """

    path: str
    title: str  # how it is written in TOML
    meaning: str
    keys: tuple[Key, ...] = ()
    names: str | None = None
    value: str | None = None
    entries: str | None = None


def _req(name: str, type_: str, meaning: str, of: str | None = None) -> Key:
    return Key(name, type_, meaning, required=True, of=of)


def _opt(name: str, type_: str, meaning: str, default: str | None = None, of: str | None = None) -> Key:
    return Key(name, type_, meaning, default=default, of=of)


_NUMBER = "number"
_STRING = "string"
_STRINGS = "list of strings"
_BOOL = "boolean"
_TABLE = "table"
_TABLES = "array of tables"

TABLES: tuple[Table, ...] = (
    Table("", "top level", "A scenario file describes one mission completely.", (
        _req("scenario", _TABLE, "the scenario's name and how it is accounted", of="scenario"),
        _req("platforms", _TABLE, "the computers: idle and busy power", of="platforms"),
        _req("radios", _TABLE, "the radio media: bandwidth and power", of="radios"),
        _req("robots", _TABLES, "the robots (one or more)", of="robots[]"),
        _req("basestation", _TABLE, "the base station (the operator's node)", of="basestation"),
        _req("network", _TABLE, "which nodes talk over which media", of="network"),
        _req("components", _TABLE, "the component types and their latencies", of="components"),
        _req("chains", _TABLES, "the applications: source, stages, sink, period", of="chains[]"),
        _opt("reference_rows", _TABLES, "configurations to compare against (`analyze` shows them as paper-row-N)",
             of="reference_rows[]"),
        _opt("migration", _TABLE, "what moving a running component costs", of="migration"),
        _opt("mission", _TABLE, "how lifetime and quality are traded", of="mission"),
        _opt("delivery", _TABLE, "what a node keeps for a sink out of its reach", of="delivery"),
        _opt("control_plane", _TABLE, "whether the team's own statuses and keep-alives are charged",
             of="control_plane"),
    )),
    Table("scenario", "[scenario]", "The scenario's name and accounting.", (
        _req("name", _STRING, "the scenario's name"),
        _opt("description", _STRING, "one line shown by `check` and in recordings", '""'),
        _opt("accounting", '"paper" or "physical"', '"paper": one message per flow per second (the paper\'s rule); '
             '"physical": one per period', '"paper"'),
        _opt("lifetime_rounding_s", "number >= 0", "lifetimes are rounded to the nearest multiple, halves up "
             "(0: no rounding)", "0.8"),
    )),
    Table("platforms", "[platforms.NAME]", "The computers, one table per platform; at least one.",
          names="platform name", value="table", entries="platforms.<platform>"),
    Table("platforms.<platform>", "[platforms.NAME]", "One computer's power.", (
        _opt("idle_w", "number >= 0", "power when idle (W); required unless `mains`", "0 when `mains`"),
        _opt("busy_w", "number >= idle_w", "power when busy (W); required unless `mains`", "idle_w when `mains`"),
        _opt("mains", _BOOL, "mains powered: pays no energy (a robot's platform may not be)", "false"),
        _opt("slowdown", "number > 0", "how many times slower than the computer running AutoPower this "
             "platform runs code: the runtime's own CPU (all but component code) is charged as that many "
             "seconds busy, part `cpu_runtime`", "none: the runtime's CPU is measured, not charged"),
        _opt("levels", _TABLE, "DVFS frequency levels; the platform's latencies are its fastest level's",
             of="platforms.<platform>.levels"),
    )),
    Table("platforms.<platform>.levels", "[platforms.NAME.levels.LEVEL]",
          "DVFS levels of a platform, one table per level; at least one when present.",
          names="level name (without `@`)", value="table", entries="platforms.<platform>.levels.<level>"),
    Table("platforms.<platform>.levels.<level>", "[platforms.NAME.levels.LEVEL]", "One frequency level.", (
        _req("idle_w", "number >= 0", "idle power at this level (W)"),
        _req("busy_w", "number >= idle_w", "busy power at this level (W)"),
        _req("latency_factor", "number >= 1", "every run takes this much longer than the platform's latency_s"),
        _opt("mhz", "number > 0", "clock frequency (documentation only)"),
        _opt("core_v", "number > 0", "core voltage (documentation only)"),
    )),
    Table("radios", "[radios.NAME]", "The radio media, one table per medium; at least one.",
          names="medium name (quote it when it has a dot: `[radios.\"802.11a\"]`)", value="table",
          entries="radios.<medium>"),
    Table("radios.<medium>", "[radios.NAME]", "One radio medium.", (
        _req("kbps", "number > 0", "bandwidth (kbit/s)"),
        _req("sleep_w", "number >= 0", "power when idle (W)"),
        _req("send_w", "number >= sleep_w", "power while sending (W)"),
        _req("receive_w", "number >= sleep_w", "power while receiving (W)"),
    )),
    Table("robots[]", "[[robots]]", "One robot; list one table per robot.", (
        _req("name", _STRING, "the robot's node name (unique; not the base station's)"),
        _req("platform", _STRING, "a battery platform (not `mains`)"),
        _req("energy_j", "number > 0", "the battery's energy at the start (J)"),
        _opt("sensors", _STRINGS, "the sensors it carries (what chains may `require`)", "[]"),
    )),
    Table("basestation", "[basestation]", "The base station: the operator's node.", (
        _req("name", _STRING, "its node name"),
        _req("platform", _STRING, "its platform (usually a `mains` one)"),
        _opt("limit_radios", _BOOL, "its radios may be at most 100 % busy too (the paper does not limit them)",
             "false"),
    )),
    Table("network", "[network]", "Which nodes talk over which media.", (
        _req("topology", '"fully-connected", "relay" or "explicit"',
             'the topology planned; "relay": only `relay` links to the base station; "explicit": `links`'),
        _opt("relay", _STRING, "the robot that links to the base station in the relay topology"),
        _opt("laptop_robot_media", "list of media", "candidate media between base station and robots, the first "
             "is the default; required for a named topology"),
        _opt("robot_robot_media", "list of media", "candidate media between robots, the first is the default; "
             "required for a named topology"),
        _opt("links", _TABLES, "the links of an explicit topology (required for it)", of="network.links[]"),
        _opt("analyze_topologies", "list of topologies", "the named topologies `analyze` explores", "[topology]"),
        _opt("loss", _TABLE, "the share of packets each listed link loses; its airtime, so its send and receive "
             "energy, is priced 1 / (1 - loss) times (the retransmissions)", "{} (no link loses)",
             of="network.loss"),
    )),
    Table("network.loss", 'loss = { "A-B" = SHARE, ... }',
          "Packet loss per link, measured or expected where the robots work: one entry per lossy link, either "
          "direction, whatever medium it uses; a link not listed loses nothing.",
          names='link `"A-B"`: two linked nodes, in either order (quoted: it has a dash)',
          value="number, 0 <= loss < 1 (0.1 for 10 %)"),
    Table("network.links[]", "[[network.links]]", "One link of an explicit topology.", (
        _req("a", _STRING, "one end (a node)"),
        _req("b", _STRING, "the other end (another node)"),
        _req("media", "list of media", "its candidate media (at least one; the first is the default)"),
        _opt("group", _STRING, "links of one group share one medium choice and the same media list", '"A-B"'),
    )),
    Table("components", "[components.NAME]", "The component types, one table per type.",
          names="component type name", value="table", entries="components.<component>"),
    Table("components.<component>", "[components.NAME]", "One component type.", (
        _req("latency_s", _TABLE, "seconds per run on each platform", of="components.<component>.latency_s"),
        _opt("implementation", '"pkg.mod:Class"', "your own component's class (with `source`)"),
        _opt("source", '"pkg.mod:Class"', "the source feeding your own component's chains (with `implementation`)"),
        _opt("variants", _TABLE, "quality variants", of="components.<component>.variants"),
    )),
    Table("components.<component>.latency_s", "latency_s = { PLATFORM = SECONDS, ... }",
          "Seconds per run; one entry for every platform (a component may run anywhere).",
          names="platform name", value="number > 0"),
    Table("components.<component>.variants", "[components.NAME.variants.VARIANT]",
          "Quality variants, in file order: the first runs when no variant is chosen.",
          names="variant name (without `@`)", value="table", entries="components.<component>.variants.<variant>"),
    Table("components.<component>.variants.<variant>", "[components.NAME.variants.VARIANT]", "One variant.", (
        _req("quality", "number in (0, 1]", "its quality; a plan's quality is the mean over its chains"),
        _opt("period_s", "number > 0", "the chain's period with this variant", "the chain's"),
        _opt("latency_s", "table: platform = number > 0", "per-run latency with this variant",
             "the component's", of="components.<component>.variants.<variant>.latency_s"),
        _opt("message_bytes", "[input, output]", "the stage's input and output message sizes", "the chain's"),
        _opt("parameters", "table of numbers or strings", "handed to the real component", "{}"),
    )),
    Table("components.<component>.variants.<variant>.latency_s", "latency_s = { PLATFORM = SECONDS, ... }",
          "Seconds per run with this variant.", names="platform name", value="number > 0"),
    Table("chains[]", "[[chains]]", "One application: a source robot's sensor, stages, a sink; list one per chain.", (
        _req("name", _STRING, "the chain's name (unique among chains and stages)"),
        _opt("source", _STRING, "the robot whose sensor feeds it; without one, the first stage is fed by its "
             "`inputs` only"),
        _opt("sink", '"source", "operator" or a node', 'where results go; "operator": the base station',
             '"source"'),
        _req("period_s", "number > 0", "seconds between two runs of its source"),
        _opt("component", _STRING, "a one-stage chain: its component (the stage is named like the chain); "
             "exactly one of `component` and `stages`"),
        _opt("stages", _TABLES, "a multi-stage chain: its stages in order", of="chains[].stages[]"),
        _req("message_bytes", "list of integers >= 0", "each hop's message: source -> first stage, ..., last stage "
             "-> sink (without a source: first stage -> ..., last stage -> sink)"),
        _opt("requires", _STRINGS, "sensors the source robot must carry", "[]"),
        _opt("pin", _STRING, "a one-stage chain: the node it must run on"),
        _opt("hosts", _STRINGS, "a one-stage chain: the only nodes it may run on"),
        _opt("min_quality", "number >= 0", "variants scoring less may not run this chain", "0"),
        _opt("keep", '"all" or "latest"', 'what a node cut off from the sink holds of its results: "all" (in '
             'order, within the hold budget) or "latest" (only the newest: a camera-like chain that wants fresh '
             'data; the ones it replaces are counted as superseded, not lost)', '"all"'),
        _opt("inputs", _TABLES, "a one-stage chain without a source: outputs of other chains' stages it takes",
             of="chains[].stages[].inputs[]"),
    )),
    Table("chains[].stages[]", "stages = [{ name, component, ... }, ...]", "One stage of a multi-stage chain.", (
        _req("name", _STRING, "the stage's name (unique among chains and stages)"),
        _req("component", _STRING, "its component type"),
        _opt("pin", _STRING, "the node it must run on"),
        _opt("hosts", _STRINGS, "the only nodes it may run on"),
        _opt("inputs", _TABLES, "outputs of other chains' stages it takes (first stage of a chain without a "
             "source only)", of="chains[].stages[].inputs[]"),
    )),
    Table("chains[].stages[].inputs[]", "inputs = [{ from, bytes }, ...]",
          "One DAG input: a flow from a stage of another chain of the same period.", (
              _req("from", _STRING, "the producing stage"),
              _req("bytes", "integer >= 0", "the message size of the flow"),
          )),
    Table("reference_rows[]", "[[reference_rows]]", "A configuration to compare against.", (
        _req("topology", '"fully-connected", "relay" or "explicit"', "the row's topology"),
        _opt("laptop_robot", _STRING, "a named topology: the base station-robot medium (required for it)"),
        _opt("robot_robot", _STRING, "a named topology: the robot-robot medium (required for it)"),
        _opt("media", _TABLE, "an explicit topology: one medium per link group",
             "each group's first medium", of="reference_rows[].media"),
        _req("allocation", _TABLE, "the node of every stage", of="reference_rows[].allocation"),
        _opt("paper_lifetime_s", "number > 0", "the lifetime the paper reports for it"),
    )),
    Table("reference_rows[].allocation", "allocation = { STAGE = NODE, ... }",
          "Where each stage runs; one entry for every stage.", names="stage name", value="node name"),
    Table("reference_rows[].media", "media = { GROUP = MEDIUM, ... }",
          "The medium of each link group of an explicit topology.", names="link group", value="one of its media"),
    Table("migration", "[migration]", "What moving a running component costs (simulate and the policies).", (
        _opt("downtime_s", "number >= 0", "the stage does not run for this long per move (plus the state's airtime)",
             "0.5"),
        _opt("cpu_s", "number >= 0", "busy CPU seconds to export and to import the state, on each end", "0.05"),
        _opt("state_bytes_default", "number >= 0", "state bytes moved for a component type not in `state_bytes`",
             "32768"),
        _opt("state_bytes", _TABLE, "state bytes moved per component type", "{}", of="migration.state_bytes"),
    )),
    Table("migration.state_bytes", "state_bytes = { COMPONENT = BYTES, ... }",
          "State bytes per component type.", names="component type name", value="number >= 0"),
    Table("mission", "[mission]", "How the planner trades lifetime against quality.", (
        _opt("quality_weight", "number in [0, 1]", "0: lifetime only (ties: higher quality); 1: quality only; "
             "between: the Pareto point maximising (1 - w)·L/L_best + w·Q", "0"),
    )),
    Table("delivery", "[delivery]", "What a node keeps for a sink out of its reach (store and forward).", (
        _opt("hold_budget_mb", "number > 0", "results a node keeps (in memory and in its journal on disk) until "
             "their sink acknowledges them; beyond it the oldest are dropped, counted apart from lost ones",
             "64"),
    )),
    Table("control_plane", "[control_plane]", "The team's own messages on every direct link: statuses, "
          "keep-alives and their acknowledgements (docs/concepts/energy-model.md).", (
        _opt("enabled", "true or false", "charge them in the model and the planner (false: the paper's "
             "assumption, Fig. 7 exactly)", "false"),
        _opt("status_period_s", "number > 0", "a change (a plan, a stage, a link) is said within this many seconds",
             "0.5"),
        _opt("heartbeat_s", "number >= status_period_s", "seconds between two statuses with nothing new in them "
             "(counts move, nothing changes): what a steady team sends", "2, or half of max_detection_s"),
        _opt("lease_s", "number > 0", "the transport's lease: a cut link or dead peer is seen after it",
             "0.5, or the longest allowed by max_detection_s"),
        _opt("max_detection_s", "number > 0", "the mission's requirement: a failure seen within this; "
             "the lease is the longest within it and the heartbeat half of it (every control cost falls with "
             "longer ones)", "none"),
        _opt("keep_alives_per_lease", "integer >= 1", "keep-alives per lease on a link that sends nothing else",
             "2"),
        _opt("status_bytes", "integer >= 0", "a robot's whole status to the base station, encoded, with its key "
             "(sent at least every 10 s)", "800"),
        _opt("status_change_bytes", "integer >= 0", "a robot's status to the base station as its change from the "
             "last whole one, encoded, with its key (sent between)", "250"),
        _opt("peer_status_bytes", "integer >= 0", "the status robots send each other, encoded, with its key", "150"),
        _opt("keep_alive_bytes", "integer >= 0", "one keep-alive message", "8"),
        _opt("packet_overhead_bytes", "integer >= 0", "IP, TCP and TLS framing around each message", "74"),
        _opt("ack_bytes", "integer >= 0", "the acknowledgement each message gets back", "52"),
        _opt("relayed_extra_bytes", "integer >= 0", "a status relayed to a base station out of direct reach: "
             "its route and signature, on every hop", "517"),
    )),
)

SCHEMA: dict[str, Table] = {t.path: t for t in TABLES}


def allowed(path: str) -> tuple[str, ...]:
    """The keys a fixed table at `path` accepts, in schema order."""
    return tuple(k.name for k in SCHEMA[path].keys)


def required(path: str) -> tuple[str, ...]:
    """The keys a fixed table at `path` must have, in schema order."""
    return tuple(k.name for k in SCHEMA[path].keys if k.required)


def unknown_keys(data: dict) -> list[str]:
    """Dotted paths of keys in a parsed scenario that the schema does not list (the schema's own check)."""
    out: list[str] = []

    def walk(obj, path: str, where: str) -> None:
        table = SCHEMA[path]
        if isinstance(obj, list):
            for i, item in enumerate(obj):
                walk(item, path, f"{where}[{i}]")
            return
        if not isinstance(obj, dict):
            return
        for name, value in obj.items():
            at = f"{where}.{name}" if where else name
            if table.names is not None:
                if table.entries is not None:
                    walk(value, table.entries, at)
                continue
            key = next((k for k in table.keys if k.name == name), None)
            if key is None:
                out.append(at)
            elif key.of is not None:
                walk(value, key.of, at)

    walk(data, "", "")
    return out


# ---- the reference page ---------------------------------------------------------------------------
def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render_markdown(level: int = 2) -> str:
    """The schema as Markdown: one section per table, one row per key."""
    hashes = "#" * level
    maps = {t.entries: t for t in TABLES if t.entries is not None}  # entries path -> its map table
    parts: list[str] = []
    for table in TABLES:
        if table.entries is not None:
            continue  # said with the table of its entries, which has the same TOML header
        heading = "Top level" if not table.path else f"`{table.title}`"
        parts.append(f"{hashes} {heading}\n")
        if table.path in maps:
            parts.append(f"{maps[table.path].meaning} `{table.title.rsplit('.', 1)[-1].rstrip(']')}`: a "
                         f"{maps[table.path].names}.\n")
        parts.append(f"{table.meaning}\n")
        if table.names is not None:
            parts.append(f"Each key is a {table.names}; its value: {table.value}.\n")
            continue
        parts.append("| key | type | required or default | meaning |")
        parts.append("| --- | --- | --- | --- |")
        for key in table.keys:
            default = key.default if key.default is None or "`" in key.default else f"`{key.default}`"
            need = "**required**" if key.required else (default or "optional, no default")
            parts.append(f"| `{key.name}` | {_cell(key.type)} | {_cell(need)} | {_cell(key.meaning)} |")
        parts.append("")
    return "\n".join(parts)
