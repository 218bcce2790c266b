"""Applications as DAGs (docs/concepts/chains.md): format, validation, evaluator, planners."""

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from autopower.errors import ScenarioError
from autopower.model.energy import evaluate
from autopower.model.loading import load_scenario, parse_scenario, resolve_scenario_path
from autopower.model.network import build_network
from autopower.planner import PlanRequest, plan
from autopower.planner.exhaustive import exhaustive
from autopower.planner.milp import solve_milp
from autopower.planner.problem import make_problem
from autopower.simulation.synthetic import random_dag_scenario

DAG = load_scenario("paper-teammap")
FIG7 = load_scenario("paper-fig7")
_, DAG_TEXT = resolve_scenario_path("paper-teammap")
AUTOPOWER = shutil.which("autopower", path=str(Path(sys.executable).parent)) or "autopower"


def edited(old: str, new: str) -> str:
    assert old in DAG_TEXT
    return DAG_TEXT.replace(old, new, 1)


def line_of(text: str, fragment: str) -> int:
    return text[: text.index(fragment)].count("\n") + 1


def test_the_shipped_dag_has_fan_in_and_fan_out():
    team = DAG.chain("TeamMap")
    assert not team.sourced and team.source == team.sink == "laptop"
    assert [(f.producer, f.consumer, f.n_bytes) for f in team.inputs] == [
        ("Loc-1", "TeamMap", 805), ("Loc-2", "TeamMap", 805), ("Loc-3", "TeamMap", 805)]
    assert team.message_bytes == (0, 600)  # no sensor hop
    loc = DAG.chain("Loc-1")  # the linear chain is unchanged: its pose still goes back to r1
    assert loc == FIG7.chain("Loc-1")


INPUTS = 'inputs = [{ from = "Loc-1", bytes = 805 }, { from = "Loc-2", bytes = 805 }, { from = "Loc-3", bytes = 805 }]'


@pytest.mark.parametrize("new, field, problem", [
    ('inputs = [{ from = "Loc-9", bytes = 805 }]', "chains[5].inputs[0].from", "unknown stage 'Loc-9'"),
    ('inputs = [{ from = "Loc-1", bytes = 805 }, { from = "Loc-1", bytes = 9 }]', "chains[5].inputs[1].from",
     "'Loc-1' listed twice"),
    ('inputs = [{ from = "Blob-2", bytes = 200 }]', "chains[5].inputs[0].from", "runs every 0.25 s"),
    ('inputs = [{ from = "Loc-1", bytes = -1 }]', "chains[5].inputs[0].bytes", "found -1"),
    ('inputs = [{ from = "Loc-1" }]', "chains[5].inputs[0]", "missing required key 'bytes'"),
    ("inputs = []", "chains[5].inputs", "found []"),
])
def test_bad_flows_name_file_line_and_field(new, field, problem):
    text = edited(INPUTS, new)
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text, "dag.toml")
    message = str(err.value)
    assert message.startswith(f"dag.toml:{line_of(text, new)}: {field}: ") and problem in message, message
    assert "\n" not in message


def test_a_cycle_is_refused_naming_it():
    # a second map fed by the first, which takes the second as an input: TeamMap > Map2 > TeamMap
    text = edited(INPUTS, INPUTS.replace("]", ', { from = "Map2", bytes = 9 }]'))
    text += """
[[chains]]
name = "Map2"
sink = "operator"
component = "TeamMap"
period_s = 2.0
inputs = [{ from = "TeamMap", bytes = 600 }]
message_bytes = [600]
"""
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text, "dag.toml")
    message = str(err.value)
    assert re.fullmatch(r"dag.toml:(\d+): chains\[(5|6)\]\.inputs\[(0|3)\]\.from: cycle "
                        r"(TeamMap > Map2 > TeamMap|Map2 > TeamMap > Map2); expected an acyclic graph.*", message), message
    line = int(message.split(":")[1])
    assert "inputs = [" in text.splitlines()[line - 1]


def test_inputs_only_on_the_first_stage_of_a_chain_without_source():
    """Fan-in into a stage its own chain also feeds is refused (the runtime joins stages fed by
    inputs alone); the line is the one of the stages list it sits in."""
    old = 'name = "Loc-1"\nsource = "r1"\nsink = "source"               # the pose goes back to the robot\ncomponent = "Loc"'
    new = ('name = "Loc-1"\nsource = "r1"\nsink = "source"\n'
           'stages = [{ name = "A", component = "Loc" }, { name = "B", component = "Loc", inputs = [{ from = "Loc-2", bytes = 5 }] }]')
    text = edited(old, new).replace("message_bytes = [1059, 805]", "message_bytes = [1059, 805, 805]", 1)
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text, "dag.toml")
    line = line_of(text, 'stages = [{ name = "A"')
    assert str(err.value).startswith(f"dag.toml:{line}: chains[0].stages[1].inputs: "
                                     "inputs on 'B', a stage its own chain feeds; expected inputs only on the first stage")


def test_same_chain_input_is_refused():
    text = edited('component = "TeamMap"\n', "")
    text = text.replace(INPUTS, 'stages = [{ name = "TeamMap", component = "TeamMap", inputs = [{ from = "Tail", bytes = 5 }] }, '
                                '{ name = "Tail", component = "TeamMap" }]')
    text = text.replace("message_bytes = [600]", "message_bytes = [600, 600]")
    text = text.replace('"TeamMap" = "laptop" }', '"TeamMap" = "laptop", "Tail" = "laptop" }')
    with pytest.raises(ScenarioError, match=r"chains\[5\]\.stages\[0\]\.inputs\[0\]\.from: 'Tail' is in the same chain"):
        parse_scenario(text, "dag.toml")


def test_validate_cli_exit_2_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(edited(INPUTS, 'inputs = [{ from = "Nope", bytes = 805 }]'))
    out = subprocess.run([AUTOPOWER, "check", str(bad)], capture_output=True, text=True)
    assert out.returncode == 2, out
    assert out.stderr.count("\n") == 1 and re.match(rf"^.*{re.escape(str(bad))}:\d+: chains\[5\]\.inputs\[0\]\.from: "
                                                    "unknown stage 'Nope'", out.stderr.strip().splitlines()[-1]), out.stderr


@pytest.mark.parametrize("accounting, extra_w", [("paper", 805 * 8 / (54000 * 1024) * 1.498),
                                                 ("physical", 805 * 8 / (54000 * 1024) * 1.498 / 2.0)])
def test_each_flow_is_routed_and_charged(accounting, extra_w):
    """TeamMap on the laptop: Loc-1 on r1 now also sends its pose r1 -> laptop; in paper accounting
    one message a second, in physical one per Loc run (every 2 s)."""
    network = build_network(DAG, "fully-connected", {"laptop-robot": "802.11a", "robot-robot": "802.11a"})
    local = {"Loc-1": "r1", "Loc-2": "r2", "Loc-3": "r3", "Blob-2": "r2", "Blob-3": "r3"}
    with_map = evaluate(DAG, network, {**local, "TeamMap": "laptop"}, accounting=accounting)
    without = evaluate(FIG7, network, local, accounting=accounting)
    radio = lambda ev: ev.robots["r1"].radios["802.11a"]
    assert radio(with_map).send_w - radio(without).send_w == pytest.approx(extra_w, rel=1e-9)
    assert with_map.robots["r1"].cpu_w == without.robots["r1"].cpu_w
    # on r1 instead, r1 pays the map's CPU, receives Loc-2's and Loc-3's poses, sends the map
    on_r1 = evaluate(DAG, network, {**local, "TeamMap": "r1"}, accounting=accounting)
    assert on_r1.utilisation["r1"] == pytest.approx(without.utilisation["r1"] + 0.02 / 2.0)
    assert radio(on_r1).receive_w > radio(without).receive_w


def test_disabling_every_input_stops_the_join():
    network = build_network(DAG, "fully-connected")
    problem = make_problem(PlanRequest(scenario=DAG, network=network, disabled_chains=frozenset({"Loc-1", "Loc-2", "Loc-3"})))
    assert "TeamMap" not in [c.name for c in problem.chains]
    assert problem.unroutable["TeamMap"] == "TeamMap cannot run: none of its inputs runs"
    some = make_problem(PlanRequest(scenario=DAG, network=network, disabled_chains=frozenset({"Loc-1"})))
    assert [f.producer for f in some.flows] == ["Loc-2", "Loc-3"]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10_000), robots=st.integers(2, 3), chains=st.integers(1, 3),
       topology=st.sampled_from(["fully-connected", "relay"]), accounting=st.sampled_from(["paper", "physical"]),
       multi_stage=st.booleans())
def test_milp_equals_exhaustive_on_random_dags(seed, robots, chains, topology, accounting, multi_stage):
    s = random_dag_scenario(seed, robots, chains, topology=topology, accounting=accounting, multi_stage=multi_stage)
    problem = make_problem(PlanRequest(scenario=s))
    assert problem.flows  # a DAG, not a chain set
    best = exhaustive(problem)
    milp = solve_milp(problem)
    if not best:
        assert milp.allocation is None
        return
    assert milp.lifetime_s == pytest.approx(best[0].lifetime_s, rel=1e-7)
    ev = evaluate(s, milp.network, milp.allocation, accounting=accounting)
    assert ev.feasible and ev.lifetime_s == pytest.approx(best[0].lifetime_s, rel=1e-7)
    # the exhaustive optimum is what the evaluator says it is (flows included)
    ev_best = evaluate(s, best[0].network, best[0].allocation, accounting=accounting)
    assert ev_best.lifetime_s == pytest.approx(best[0].lifetime_s, rel=1e-9)


def test_reasons_name_the_flows_a_stage_moves():
    network = build_network(DAG, "fully-connected", {"laptop-robot": "gsm", "robot-robot": "802.11a"})
    p = plan(PlanRequest(scenario=DAG, network=network))
    assert set(p.reasons) == set(DAG.stage_names())
    why = p.reasons["TeamMap"]
    assert "Here, flow Loc-1>TeamMap stays on laptop" in why, why
    assert "On r1, flow Loc-1>TeamMap (805 B) laptop → r1 (gsm); flow Loc-2>TeamMap" in why, why


@pytest.mark.parametrize("seed", [3, 7, 11])
def test_time_sharing_bound_on_dags_column_generation_matches_enumeration(seed):
    """The bound's two methods (enumeration; column generation priced by the MILP) agree on DAGs,
    and every phase of its schedule is feasible under the evaluator (flows charged)."""
    from autopower.planner import timesharing

    s = random_dag_scenario(seed, 3, 3, energy_spread=0.6, accounting="physical")
    problem = make_problem(PlanRequest(scenario=s))
    p = plan(PlanRequest(scenario=s))
    full = timesharing._by_enumeration(problem)
    cg = timesharing._by_column_generation(problem, [(p.network, p.allocation)], 60)
    assert cg.lifetime_s == pytest.approx(full.lifetime_s, rel=1e-5)
    assert full.lifetime_s >= p.evaluation.lifetime_s * (1 - 1e-9)
    for phase in full.schedule:
        ev = evaluate(s, phase.network, phase.allocation, accounting="physical")
        assert ev.feasible
        assert {r: rp.total_w for r, rp in ev.robots.items()} == pytest.approx(phase.power_w, rel=1e-9)


def test_dag_inputs_with_dvfs_levels_are_refused_not_planned_wrong():
    """The variant and level search does not charge DAG flows yet: such a file is refused at its
    first fan-in, naming what it combines."""
    text = edited("[platforms.laptop]", "[platforms.sitsang.levels.\"100MHz\"]\nidle_w = 1.25\n"
                  "busy_w = 1.39\nlatency_factor = 4.0\n\n[platforms.laptop]")
    with pytest.raises(ScenarioError, match=r"DAG inputs together with platforms\.sitsang\.levels"):
        parse_scenario(text, "dag.toml")
