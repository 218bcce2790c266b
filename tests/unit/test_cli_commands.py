"""`autopower`'s commands are imported on demand (`autopower.cli.main.COMMAND_MODULES`): the table
must name every command a module of `autopower.cli` defines, and an operator's command must not
pull in the planner."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys

import pytest

import autopower.cli
from autopower.cli.main import COMMAND_MODULES, cli


def test_every_command_a_module_defines_is_reachable_by_its_name():
    defined = {}
    for info in pkgutil.iter_modules(autopower.cli.__path__):
        module = importlib.import_module(f"autopower.cli.{info.name}")
        for command in getattr(module, "COMMANDS", ()):
            defined.setdefault(command.name, set()).add(info.name)
    assert set(defined) == set(COMMAND_MODULES)
    for name, module in COMMAND_MODULES.items():
        assert module in defined[name], (name, module)
        assert cli.get_command(None, name).name == name
    assert cli.get_command(None, "nope") is None


def test_an_operators_command_loads_no_planner_numpy_or_coordinator():
    code = ("import sys; from autopower.cli.main import cli; cli.get_command(None, 'status'); "
            "cli.get_command(None, 'fault'); cli.get_command(None, 'chain'); "
            "print(sorted(m for m in ('numpy', 'networkx', 'highspy', 'autopower.planner', "
            "'autopower.basestation.coordinator', 'rerun') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("command", [["agent", "--robot", "r1"], ["basestation"]])
def test_a_heartbeat_shorter_than_the_status_period_is_refused_before_anything_starts(command):
    from pathlib import Path

    autopower = str(Path(sys.executable).parent / "autopower")
    out = subprocess.run([autopower, *command, "--status-period", "0.5", "--heartbeat", "0.2"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stdout == "", (out.returncode, out.stdout)
    assert "--heartbeat 0.2 is shorter than --status-period 0.5" in out.stderr, out.stderr
