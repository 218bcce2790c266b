"""The TeamMap fan-in component: real work on real localisation outputs, migratable state."""

import numpy as np
import pytest

from autopower.chains import decode_estimate, make_component, make_source
from autopower.chains.base import ComponentStateError, MalformedInputError
from autopower.chains.teammap import CELL_M, JoinSource, TeamMap, decode_join, decode_map, encode_join


def real_estimates(steps: int) -> list[dict[str, bytes]]:
    """Each robot's real MCL output for steps 0..steps-1 (its own source and localiser)."""
    out = [dict() for _ in range(steps)]
    for k, robot in enumerate(("r1", "r2", "r3")):
        source, mcl = make_source("Loc", robot, 11 + k), make_component("Loc", robot, 11 + k)
        for seq in range(steps):
            out[seq][f"Loc-{k + 1}"] = mcl.run(source.produce(seq))
    return out


def test_merges_real_poses_and_grows_the_explored_area():
    estimates = real_estimates(8)
    team = TeamMap("laptop", 0)
    maps = [decode_map(team.run(encode_join(step, inputs, []))) for step, inputs in enumerate(estimates)]
    assert all(set(m["robots"]) == {"r1", "r2", "r3"} for m in maps)
    areas = [m["explored_m2"] for m in maps]
    assert areas[0] > 0 and areas == sorted(areas) and areas[-1] > areas[0]
    # the merged poses are the localisers' estimates, and the grid holds the explored cells
    for k, robot in enumerate(("r1", "r2", "r3")):
        assert maps[-1]["robots"][robot]["pose"] == pytest.approx(list(decode_estimate(estimates[-1][f"Loc-{k + 1}"]).pose))
    bits = np.unpackbits(np.frombuffer(maps[-1]["grid"], dtype=np.uint8)).sum()
    assert bits * CELL_M * CELL_M == maps[-1]["explored_m2"]


def test_a_missing_input_ages_that_robot_and_is_reported():
    estimates = real_estimates(3)
    team = TeamMap("laptop", 0)
    team.run(encode_join(0, estimates[0], []))
    without = {k: v for k, v in estimates[1].items() if k != "Loc-2"}
    out = decode_map(team.run(encode_join(1, without, ["Loc-2"])))
    assert out["missing"] == ["Loc-2"] and out["robots"]["r2"]["age_steps"] == 1
    assert out["robots"]["r1"]["age_steps"] == 0 and team.missed == 1


def test_state_round_trip_continues_identically():
    estimates = real_estimates(6)
    a, b = TeamMap("laptop", 0), TeamMap("laptop", 0)
    for step in range(3):
        a.run(encode_join(step, estimates[step], []))
    b.import_state(a.export_state())
    for step in range(3, 6):
        assert a.run(encode_join(step, estimates[step], [])) == b.run(encode_join(step, estimates[step], []))


@pytest.mark.parametrize("payload", [b"", b"\x81\xa1v\x02", encode_join(0, {"Loc-1": b"not an estimate"}, [])])
def test_malformed_input_is_a_clear_error(payload):
    with pytest.raises(MalformedInputError):
        TeamMap("laptop", 0).run(payload)


def test_corrupt_state_is_refused():
    with pytest.raises(ComponentStateError):
        TeamMap("laptop", 0).import_state(b"\x01\x02")


def test_profiling_source_joins_three_robots():
    join = decode_join(JoinSource("laptop", 0).produce(4))
    assert join["step"] == 4 and sorted(join["inputs"]) == ["Loc-1", "Loc-2", "Loc-3"] and join["missing"] == []
    assert len(TeamMap("laptop", 0).run(JoinSource("laptop", 0).produce(4))) <= 600  # the scenario's message_bytes
