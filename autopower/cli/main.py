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
    simulate,
    team,
    testbed,
)
from autopower.cli.entry import run_command


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def cli() -> None:
    """AutoPower: energy-aware placement of robot software across a multi-robot team.

    SCENARIO is a built-in name (paper-fig7, paper-fig8, ...) or a path to a .toml file.
    """


for _module in (analysis, evaluate, profile, simulate, replay, recording, processes, team, operator, fault, demo,
                deploy, testbed, quality):
    for _command in _module.COMMANDS:
        cli.add_command(_command)


def main() -> None:
    run_command(cli, prog_name="autopower")


if __name__ == "__main__":
    main()
