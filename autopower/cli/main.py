"""The `autopower` command line.

Every AutoPowerError becomes one line on stderr and exit status 2: what was wrong, where, and
what to do. Tracebacks are for bugs only.
"""

from __future__ import annotations

import click

from autopower.cli import (
    analysis,
    demo,
    deploy,
    evaluate,
    fault,
    operator,
    processes,
    profile,
    quality,
    recording,
    replay,
    sim,
    simulate,
    team,
    testbed,
)
from autopower.cli.entry import run_command


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


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Print the versions of autopower and of the libraries it talks through, and exit.")
def cli() -> None:
    """AutoPower: energy-aware placement of robot software across a multi-robot team.

    SCENARIO is a built-in name (paper-fig7, paper-fig8, ...) or a path to a .toml file.
    """


for _module in (analysis, evaluate, profile, simulate, sim, replay, recording, processes, team, operator, fault, demo,
                deploy, testbed, quality):
    for _command in _module.COMMANDS:
        cli.add_command(_command)


def main() -> None:
    run_command(cli, prog_name="autopower")


if __name__ == "__main__":
    main()
