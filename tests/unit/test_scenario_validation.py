"""Malformed scenarios get an error naming the file, line, field, what was found and expected."""

from importlib import resources

import pytest

from autopower.errors import ScenarioError
from autopower.model.loading import builtin_scenarios, load_scenario, parse_scenario
from autopower.model.network import build_network

PAPER = (resources.files("autopower.scenarios") / "paper-fig7.toml").read_text()


def broken(old: str, new: str, count: int = 1) -> str:
    assert old in PAPER, old
    return PAPER.replace(old, new, count)


def error_of(text: str) -> str:
    with pytest.raises(ScenarioError) as info:
        parse_scenario(text, "mission.toml")
    return str(info.value)


def test_builtins_resolve_by_name():
    assert {"paper-fig7", "paper-fig8"} <= set(builtin_scenarios())
    assert load_scenario("paper-fig8").robot("r1").energy_j == 32000


def test_path_loads(tmp_path):
    path = tmp_path / "m.toml"
    path.write_text(PAPER)
    assert load_scenario(path).name == "paper-fig7"


def test_missing_file_says_what_to_do(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file.*built-in names: paper-fig7"):
        load_scenario(tmp_path / "nope.toml")


def test_toml_syntax_error_has_position():
    msg = error_of(broken('name = "r2"', 'name = "r2'))
    assert "mission.toml: not valid TOML" in msg and "line" in msg


def test_unknown_key_is_an_error_with_line():
    text = broken("idle_w = 1.34", "idle_w = 1.34\nidel_w = 1.0")
    msg = error_of(text)
    assert "platforms.sitsang.idel_w: unknown key" in msg
    assert "mission.toml:" in msg and "busy_w" in msg
    line = int(msg.split("mission.toml:")[1].split(":")[0])
    assert text.splitlines()[line - 1] == "idel_w = 1.0"


def test_negative_energy_named_with_robot_index_and_line():
    msg = error_of(broken("energy_j = 64000", "energy_j = -5"))
    assert "robots[0].energy_j: found -5" in msg and "a number > 0" in msg
    line = int(msg.split("mission.toml:")[1].split(":")[0])
    assert "energy_j = -5" in PAPER.replace("energy_j = 64000", "energy_j = -5", 1).splitlines()[line - 1]


def test_wrong_type():
    msg = error_of(broken("period_s = 0.25", 'period_s = "fast"'))
    assert "period_s: found 'fast'" in msg and "expected a number" in msg


def test_pinned_to_missing_robot():
    msg = error_of(broken('component = "Loc"', 'component = "Loc"\npin = "r9"'))
    assert "chains[0].pin: found 'r9'" in msg and "r1, r2, r3, laptop" in msg


def test_chain_needs_camera_on_source():
    msg = error_of(broken('source = "r2"\nsink = "operator"', 'source = "r1"\nsink = "operator"'))
    assert "requires: source robot r1 lacks camera" in msg


def test_unknown_medium_in_candidates():
    msg = error_of(broken('laptop_robot_media = ["802.11a", "gsm"]', 'laptop_robot_media = ["802.11a", "lte"]'))
    assert "network.laptop_robot_media: found 'lte'" in msg and "802.11a, bluetooth, gsm" in msg


def test_message_sizes_must_match_stages():
    msg = error_of(broken("message_bytes = [1059, 805]", "message_bytes = [1059]"))
    assert "message_bytes" in msg and "2 non-negative integers" in msg


def test_unroutable_chain_reported_before_running():
    text = PAPER.replace('topology = "fully-connected"', 'topology = "explicit"', 1).replace(
        'analyze_topologies = ["fully-connected", "relay"]',
        'analyze_topologies = ["explicit"]\n[[network.links]]\na = "r1"\nb = "laptop"\nmedia = ["802.11a"]\n'
        '[[network.links]]\na = "r1"\nb = "r2"\nmedia = ["bluetooth"]\n')
    msg = error_of(text)
    assert "chain Loc-3" in msg or "chain Blob-3" in msg
    assert "cannot be reached from r3" in msg


def test_explicit_topology_loads_and_routes_multi_hop():
    text = PAPER.replace('topology = "fully-connected"', 'topology = "explicit"', 1).replace(
        'analyze_topologies = ["fully-connected", "relay"]',
        'analyze_topologies = ["explicit"]\n'
        + "".join(f'[[network.links]]\na = "{a}"\nb = "{b}"\nmedia = ["{m}"]\n'
                  for a, b, m in [("r1", "laptop", "802.11a"), ("r1", "r2", "802.11a"), ("r2", "r3", "802.11a")]))
    s = parse_scenario(text, "chain.toml")
    network = build_network(s)
    assert [hop[:2] for hop in network.route("r3", "laptop")] == [("r3", "r2"), ("r2", "r1"), ("r1", "laptop")]


def test_duplicate_robot():
    msg = error_of(broken('name = "r2"', 'name = "r1"'))
    assert "duplicate node name 'r1'" in msg


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "+nan"])
@pytest.mark.parametrize("old", ["energy_j = 64000", "idle_w = 1.34", "kbps = ", "period_s = "])
def test_non_finite_numbers_refused_with_file_line_and_field(old, value):
    if old.endswith("= "):  # replace the whole value after the key
        line = next(l for l in PAPER.splitlines() if l.strip().startswith(old))
        old, text = line, PAPER.replace(line, line.split("=")[0] + f"= {value}", 1)
    else:
        text = PAPER.replace(old, old.split("=")[0] + f"= {value}", 1)
    msg = error_of(text)
    assert "a finite number" in msg or "a number > 0" in msg, msg
    where = int(msg.split("mission.toml:")[1].split(":")[0])
    assert value in text.splitlines()[where - 1]


def test_huge_integers_refused_not_overflowing():
    msg = error_of(broken("energy_j = 64000", "energy_j = " + "9" * 400))
    assert "robots[0].energy_j" in msg and "magnitude at most" in msg
    msg = error_of(broken("message_bytes = [1059, 805]", "message_bytes = [1059, " + "9" * 30 + "]"))
    assert "message_bytes" in msg and "at most" in msg


def test_non_utf8_file_refused_with_its_line(tmp_path):
    path = tmp_path / "m.toml"
    path.write_bytes(PAPER.encode().replace(b'name = "r2"', b'name = "r\xff2"', 1))
    with pytest.raises(ScenarioError, match=r"m.toml:\d+: not UTF-8 text"):
        load_scenario(path)


def test_over_deep_nesting_refused():
    for nested in ("x = " + "[" * 5000 + "]" * 5000, "x = " + "{a=" * 400 + "1" + "}" * 400):
        msg = error_of(PAPER + "\n" + nested + "\n")
        assert "nested" in msg and "deep" in msg


def test_a_directory_or_unreadable_path_is_one_clear_error(tmp_path):
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path)
    with pytest.raises(ScenarioError, match="neither a scenario file nor a built-in"):
        load_scenario("x" * 5000)


def test_the_hold_budget_is_read_in_megabytes_and_must_be_positive():
    assert load_scenario("paper-fig7").hold_budget_bytes == 64 * 2**20  # the default
    text = PAPER + "\n[delivery]\nhold_budget_mb = 0.5\n"
    assert parse_scenario(text, "budget.toml").hold_budget_bytes == 2**19
    for bad in ("0", "-3", '"lots"'):
        message = error_of(PAPER + f"\n[delivery]\nhold_budget_mb = {bad}\n")
        assert "delivery.hold_budget_mb" in message, message
