"""Which tests CI may run on every core at once (`./run tests` runs them first, with pytest-xdist).

A test is marked ``parallel`` when it needs no live team and holds no wall-clock bound that a busy
core would break: every unit test, and the simulator's tests (their clock is simulated, their
verdict depends on the seed alone). The rest (live teams, namespaces, timed bounds) run one at a
time after them, on a machine otherwise quiet.
"""

from __future__ import annotations

from pathlib import Path

import pytest

UNIT = Path(__file__).parent / "unit"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.is_relative_to(UNIT):
            item.add_marker(pytest.mark.parallel)
