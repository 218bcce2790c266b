"""How every `autopower` entry point reports errors: one line, exit 2, never a traceback."""

from __future__ import annotations

import sys

import click

from autopower.errors import AutoPowerError


def run_command(command: click.Command, args: list[str] | None = None, prog_name: str | None = None) -> None:
    """Run a click command the way users meet it: AutoPowerError -> "error: ..." and exit 2."""
    try:
        command.main(args=args, prog_name=prog_name, standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.UsageError as exc:  # one line, like every other mistake, with where to look
        where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
        click.echo(f"error: {exc.format_message()}{where}", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except AutoPowerError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)
