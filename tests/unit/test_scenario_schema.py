"""The scenario schema (`autopower.model.schema`) is the loader's list of keys and the reference
page's source: every key a shipped scenario uses is in it, a key not in it is refused with the
loader's error, a required key missing is named, and the rendered page lists every key."""

from __future__ import annotations

import copy
import re
from pathlib import Path

import pytest

from autopower.errors import ScenarioError
from autopower.model import schema
from autopower.model.loading import ScenarioParser, builtin_scenarios, load_toml, parse_scenario, resolve_scenario_path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "reference" / "scenario.md"

# The tables no shipped scenario has: an explicit topology with a link group, a multi-stage chain,
# an explicit reference row, [mission], a lossy link; with variants and levels too.
COVER = """
[scenario]
name = "schema-cover"
[platforms.board]
idle_w = 1.0
busy_w = 2.0
[platforms.board.levels.slow]
idle_w = 0.8
busy_w = 1.2
latency_factor = 2.0
[platforms.base]
mains = true
[radios.wifi]
kbps = 1000
sleep_w = 0.01
send_w = 1.0
receive_w = 1.0
[basestation]
name = "base"
platform = "base"
[[robots]]
name = "r1"
platform = "board"
energy_j = 1000
sensors = ["camera"]
[delivery]
hold_budget_mb = 8
[network]
topology = "explicit"
loss = { "r1-base" = 0.1 }
[[network.links]]
a = "r1"
b = "base"
media = ["wifi"]
group = "uplink"
[components.A]
latency_s = { board = 0.01, base = 0.001 }
[components.B]
latency_s = { board = 0.01, base = 0.001 }
[components.B.variants.full]
quality = 1.0
[[chains]]
name = "AB"
source = "r1"
sink = "operator"
period_s = 1.0
stages = [{ name = "A1", component = "A" }, { name = "B1", component = "B" }]
message_bytes = [100, 50, 10]
[[reference_rows]]
topology = "explicit"
media = { uplink = "wifi" }
allocation = { A1 = "r1", B1 = "base" }
[migration]
downtime_s = 0.1
state_bytes = { A = 10 }
[mission]
quality_weight = 0.5
[control_plane]
enabled = true
max_detection_s = 3.0
status_bytes = 900
"""


def documents() -> list[tuple[str, dict]]:
    out = []
    for name in builtin_scenarios():
        where, text = resolve_scenario_path(name)
        out.append((name, load_toml(text, where)))
    return [*out, ("schema-cover", load_toml(COVER, "schema-cover"))]


def locations(data: dict) -> dict[str, tuple[str, list]]:
    """schema path -> (dotted path, key path into `data`) of the first table there, for every table."""
    found: dict[str, tuple[str, list]] = {}

    def walk(obj, path: str, where: str, keys: list) -> None:
        table = schema.SCHEMA[path]
        if isinstance(obj, list):
            for i, item in enumerate(obj):
                walk(item, path, f"{where}[{i}]", [*keys, i])
            return
        if not isinstance(obj, dict):
            return
        found.setdefault(path, (where, keys))
        for name, value in obj.items():
            at = f"{where}.{name}" if where else name
            if table.names is not None:
                if table.entries is not None:
                    walk(value, table.entries, at, [*keys, name])
                continue
            key = next(k for k in table.keys if k.name == name)
            if key.of is not None:
                walk(value, key.of, at, [*keys, name])

    walk(data, "", "", [])
    return found


def first_locations() -> dict[str, tuple[dict, str, list]]:
    out: dict[str, tuple[dict, str, list]] = {}
    for _, data in documents():
        for path, (where, keys) in locations(data).items():
            out.setdefault(path, (data, where, keys))
    return out


FIXED = [t.path for t in schema.TABLES if t.names is None]


def parse(data: dict) -> None:
    ScenarioParser(data, "", "<test>").scenario()


def dig(data: dict, keys: list):
    for k in keys:
        data = data[k]
    return data


def test_every_shipped_scenario_and_the_cover_file_load():
    for _, data in documents():
        parse(data)  # the cover file is a valid scenario too


@pytest.mark.parametrize("name", [*builtin_scenarios(), "schema-cover"])
def test_every_key_of_a_shipped_scenario_is_in_the_schema(name):
    data = dict(documents())[name]
    assert schema.unknown_keys(data) == []


def test_the_test_files_reach_every_table_of_the_schema():
    assert sorted(set(schema.SCHEMA) - set(first_locations())) == []


@pytest.mark.parametrize("path", FIXED)
def test_a_key_not_in_the_schema_is_refused_with_the_loaders_error(path):
    base, where, keys = first_locations()[path]
    data = copy.deepcopy(base)
    dig(data, keys)["bogus_key"] = 1
    with pytest.raises(ScenarioError) as err:
        parse(data)
    if path == "chains[].stages[].inputs[]":  # a DAG input is checked as a whole
        assert "and nothing else" in str(err.value)
        return
    field = f"{where}.bogus_key" if where else "bogus_key"
    allowed = ", ".join(sorted(schema.allowed(path)))
    assert f"{field}: unknown key; expected one of {allowed} (check the spelling)" in str(err.value)


REQUIRED = [(t.path, k.name) for t in schema.TABLES for k in t.keys if k.required]


@pytest.mark.parametrize("path,key", REQUIRED, ids=[f"{p or 'top'}:{k}" for p, k in REQUIRED])
def test_a_required_key_missing_is_named(path, key):
    base, _, keys = first_locations()[path]
    data = copy.deepcopy(base)
    del dig(data, keys)[key]
    with pytest.raises(ScenarioError, match=f"missing required key.* '{key}'"):
        parse(data)


def test_every_table_and_key_is_on_the_rendered_page():
    text = schema.render_markdown(level=3)
    sections = re.split(r"^### ", text, flags=re.M)[1:]
    for table in schema.TABLES:
        if table.entries is not None:  # said with its entries' table
            assert any(table.meaning in s for s in sections), table.path
            continue
        heading = "Top level" if not table.path else f"`{table.title}`"
        [section] = [s for s in sections if s.startswith(heading + "\n") and table.meaning in s]
        for key in table.keys:
            assert f"| `{key.name}` |" in section, (table.path, key.name)


def test_the_page_has_the_marker_and_its_examples_load():
    text = PAGE.read_text(encoding="utf-8")
    hook = (ROOT / "docs" / "hooks" / "scenario_reference.py").read_text(encoding="utf-8")
    marker = re.search(r'MARKER = "(.*)"', hook).group(1)
    assert text.count(marker) == 1
    blocks = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    scenario = parse_scenario("\n".join(blocks), str(PAGE))
    assert scenario.components["Blob"].variants and scenario.platforms["sitsang"].levels
