"""The `autopower` command line.

Every AutoPowerError becomes one line on stderr and exit status 2: what was wrong, where, and
what to do. Tracebacks are for bugs only.
"""

from __future__ import annotations

import importlib

import click

from autopower.cli.entry import run_command

# Each command and the module of `autopower.cli` that defines it (in its COMMANDS), imported only
# when the command runs: `autopower status` then loads no planner, numpy or Rerun (1.3 s -> 0.2 s
# a call, and operators script it). A test checks the table against every module's COMMANDS.
COMMAND_MODULES = {
    "agent": "processes", "analyze": "analysis", "basestation": "processes", "chain": "operator",
    "check": "analysis", "demo": "demo", "deploy": "deploy", "evaluate": "evaluate", "fault": "fault",
    "migrate": "operator", "plan": "analysis", "profile": "profile", "quality": "quality",
    "recording": "recording", "replay": "replay", "scenarios": "scenarios", "sim": "sim",
    "simulate": "simulate", "status": "operator", "testbed": "testbed", "up": "team",
}


def _versions() -> str:
    """This package's version and those of what a bug report needs (Zenoh's wire protocol, Rerun's
    file format and HiGHS change between releases)."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    def of(dist: str) -> str:
        try:
            return version(dist)
        except PackageNotFoundError:
            return "not installed"

    deps = ", ".join(f"{d} {of(d)}" for d in ("eclipse-zenoh", "rerun-sdk", "highspy", "numpy"))
    return f"autopower {of('autopower')} ({deps}; Python {platform.python_version()})"


def _print_version(ctx, _param, value) -> None:
    if value and not ctx.resilient_parsing:
        click.echo(_versions())
        ctx.exit()


class _CommandsOnDemand(click.Group):
    """A group whose commands are imported when named (`COMMAND_MODULES`)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMAND_MODULES)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        module = COMMAND_MODULES.get(name)
        if module is None:
            return None
        commands = importlib.import_module(f"autopower.cli.{module}").COMMANDS
        return next(c for c in commands if c.name == name)


@click.group(cls=_CommandsOnDemand, context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Print the versions of autopower and of the libraries it talks through, and exit.")
def cli() -> None:
    """AutoPower: energy-aware placement of robot software across a multi-robot team.

    SCENARIO is a built-in name (paper-fig7, paper-fig8, ...) or a path to a .toml file.
    """



def main() -> None:
    run_command(cli, prog_name="autopower")


if __name__ == "__main__":
    main()
