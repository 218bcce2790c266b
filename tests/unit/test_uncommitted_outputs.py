"""An output delivered to a sink on its own node is safe only once the sink has written it down.

The base station is the operator's sink and often hosts the chain's last stage too. Its outputs then
never cross a link: the node acknowledges them to itself. Acknowledged before the sink's commit, its
custody let them go, the stage reported their inputs run, and a move of the stage said so to their
producer, which let the inputs go: a kill before the commit lost the outputs for good (simulator
seed 4024). Here: the node's own custody keeps such outputs until the commit, and a stage that moves
takes the outputs only its old host's memory holds with its state.
"""

from __future__ import annotations

from autopower.basestation.coordinator import CoordinatorConfig
from autopower.model.loading import load_scenario
from autopower.node.ports import NodeStores
from autopower.node.sink_store import SinkStore
from autopower.protocol import MigrateCommand
from tests.unit.sim_team import SimTeam
from tests.unit.test_agent_migration import FC, check_exactly_once, collect

CHAIN = "Blob-2"


def results_held(team: SimTeam, node: str) -> list[tuple[int, int, int]]:
    """(run, seq, attempt) of the chain's results the node keeps in custody for its sink."""
    rt = team.nodes[node]
    target = len(rt.chains[CHAIN].stages)
    return sorted((run, seq, held.frame.attempt)
                  for (run, seq), held in rt.custody.hops.get((CHAIN, target), {}).items())


def team_with_stage_on_the_laptop(tmp_path) -> tuple[SimTeam, dict]:
    sc = load_scenario("paper-fig7")
    team = SimTeam(sc, config=CoordinatorConfig(speed=1.0, media=FC, auto_replan=False, pins={CHAIN: "laptop"}),
                   stores={"laptop": NodeStores(sink_store=SinkStore(tmp_path / "laptop.sinks.json"))})
    outputs = collect(team)
    team.join()
    team.run_until(5.0)  # no status: the sink has committed nothing
    return team, outputs


def test_a_local_sinks_outputs_stay_in_custody_until_it_commits_them(tmp_path):
    team, _ = team_with_stage_on_the_laptop(tmp_path)
    laptop = team.nodes["laptop"]
    delivered = laptop.sinks[CHAIN].contiguous
    assert delivered > 10
    # delivered here, acknowledged to itself every 0.1 s, yet kept: the sink has not written them down
    assert [seq for _, seq, _ in results_held(team, "laptop")] == list(range(delivered))
    laptop.commit_sinks()
    team.clock.set(team.clock.t + 0.2)
    laptop.on_timer()
    assert results_held(team, "laptop") == []


def test_a_moving_stage_takes_the_outputs_only_its_old_hosts_memory_holds(tmp_path):
    team, outputs = team_with_stage_on_the_laptop(tmp_path)
    uncommitted = [(run, seq) for run, seq, _ in results_held(team, "laptop")]
    assert uncommitted
    team.coordinator.on_operator(MigrateCommand(stage=CHAIN, to_node="r2"))
    team.pump()
    assert team.coordinator.placing.placement[CHAIN] == "r2"
    assert team.nodes["r2"].counters.get("outputs-adopted") == len(uncommitted)
    # kept on r2 as resends (a sink that has one drops the copy as redundant), not sent again yet
    adopted = results_held(team, "r2")
    assert [(run, seq) for run, seq, _ in adopted][:len(uncommitted)] == uncommitted
    assert all(attempt >= 1 for _, seq, attempt in adopted if (0, seq) in uncommitted)
    # once the laptop commits and acknowledges, both let them go, and every output arrived once
    team.run_exchanging_statuses(10.0)
    assert not [1 for run, seq, _ in results_held(team, "r2") if (run, seq) in uncommitted]
    assert not [1 for run, seq, _ in results_held(team, "laptop") if (run, seq) in uncommitted]
    check_exactly_once(team, outputs)
