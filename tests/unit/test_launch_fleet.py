"""`LocalTeam` (autopower.launch.localhost) on fleets: a node's Zenoh connections are its own links,
and the team's processes share compiled modules instead of compiling them each."""

from __future__ import annotations

import os
import stat
from collections import Counter

import pytest

from autopower.launch.localhost import LocalTeam, TeamSpec, child_environment
from autopower.model.network import build_network
from autopower.simulation.synthetic import paper_fleet


@pytest.fixture
def state(tmp_path, monkeypatch):
    monkeypatch.setenv("AUTOPOWER_STATE_DIR", str(tmp_path / "state"))
    return tmp_path / "state"


@pytest.fixture
def cache(tmp_path):
    return tmp_path / "cache"


@pytest.mark.parametrize("topology", ["neighbours", "fully-connected"])
def test_each_node_connects_over_exactly_its_own_links(tmp_path, state, topology):
    text, scenario = paper_fleet(50, topology=topology, neighbours=2)
    path = tmp_path / "fleet.toml"
    path.write_text(text)
    team = LocalTeam(TeamSpec(scenario=str(path), proxied_links=True, secure=False, log_dir=tmp_path / "logs"),
                     scenario)
    try:
        links = build_network(scenario).links
        per_node = Counter(n for l in links for n in (l.a, l.b))
        connections: Counter = Counter()
        for node, endpoints in team.connects.items():
            connections[node] += len(endpoints)  # the connections it opens ...
        for pair in team.proxies:
            later = max(pair, key=team.nodes.index)
            connections[next(iter(pair - {later}))] += 1  # ... and the ones it accepts
        assert len(team.proxies) == len(links)
        assert connections == per_node
        if topology == "neighbours":  # O(its own links): 4 ring neighbours and the base station
            assert max(per_node[r.name] for r in scenario.robots) == 5 and per_node["laptop"] == 50
        else:
            assert per_node["r1"] == 50  # the full mesh: every robot to every other
    finally:
        for proxy in team.proxies.values():
            proxy.close()


def test_children_share_a_private_bytecode_cache_when_the_user_forbids_writing_beside_the_sources(cache):
    env = child_environment({"PATH": "/bin", "PYTHONDONTWRITEBYTECODE": "1", "XDG_CACHE_HOME": str(cache)})
    assert "PYTHONDONTWRITEBYTECODE" not in env and env["PYTHONUNBUFFERED"] == "1"
    assert env["PYTHONPYCACHEPREFIX"] == str(cache / "autopower" / "pycache")
    assert stat.S_IMODE(os.stat(cache / "autopower" / "pycache").st_mode) == 0o700
    # left alone: a user who writes bytecode, or who chose a cache of their own
    assert child_environment({"PATH": "/bin"}) == {"PATH": "/bin", "PYTHONUNBUFFERED": "1"}
    own = {"PYTHONDONTWRITEBYTECODE": "1", "PYTHONPYCACHEPREFIX": "/elsewhere"}
    assert child_environment(own) == {**own, "PYTHONUNBUFFERED": "1"}


def test_precompile_fills_the_private_cache_before_the_children_start(cache):
    import sys

    import autopower.launch.localhost as localhost

    env = child_environment({"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "PYTHONDONTWRITEBYTECODE": "1",
                             "XDG_CACHE_HOME": str(cache)})
    localhost.precompile(env)
    source = os.path.abspath(localhost.__file__)
    folder = os.path.join(env["PYTHONPYCACHEPREFIX"], os.path.dirname(source).lstrip(os.sep))
    compiled = os.path.join(folder, f"localhost.{sys.implementation.cache_tag}.pyc")
    assert os.path.getmtime(compiled) >= os.path.getmtime(source)
