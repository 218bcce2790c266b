"""How every `autopower` entry point reports errors: one line, exit 2, never a traceback.

The JSON contract (docs/reference/json-output.md): a command run with `--json` prints exactly one JSON
object on stdout, also when it fails. On failure that object is `{"error": "<the one line>",
"exit_code": N}`; the same line goes to stderr as `error: ...` and the exit status is the
usual one (2 for bad input, 130 when interrupted, 1 for a bug, whose traceback stays on stderr).
"""

from __future__ import annotations

import json
import signal
import sys

import click

from autopower.errors import AutoPowerError


def _json_error(wanted: bool, message: str, exit_code: int) -> None:
    if wanted:
        click.echo(json.dumps({"error": message, "exit_code": exit_code}))


def run_command(command: click.Command, args: list[str] | None = None, prog_name: str | None = None) -> None:
    """Run a click command the way users meet it: AutoPowerError -> "error: ..." and exit 2."""
    argv = list(sys.argv[1:] if args is None else args)
    # Ctrl-C (SIGINT) is how `up`, `testbed up` and `demo` are stopped, also by scripts (`kill -INT`).
    # A command started in the background by a shell without job control inherits SIGINT ignored,
    # and Python keeps it so: such a team could not be stopped but by SIGTERM or SIGKILL.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # Options after "--" are arguments, not flags.
    as_json = "--json" in (argv[:argv.index("--")] if "--" in argv else argv)
    try:
        command.main(args=argv, prog_name=prog_name, standalone_mode=False)
    except click.exceptions.Abort:
        _json_error(as_json, "aborted", 130)
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.UsageError as exc:  # one line, like every other mistake, with where to look
        where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
        _json_error(as_json, f"{exc.format_message()}{where}", exc.exit_code)
        click.echo(f"error: {exc.format_message()}{where}", err=True)
        sys.exit(exc.exit_code)
    except click.ClickException as exc:
        _json_error(as_json, exc.format_message(), exc.exit_code)
        exc.show()
        sys.exit(exc.exit_code)
    except AutoPowerError as exc:
        _json_error(as_json, str(exc), 2)
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        _json_error(as_json, "interrupted", 130)
        sys.exit(130)
    except Exception as exc:
        # A bug: the traceback is for the developer (stderr), the object for whoever parses stdout.
        _json_error(as_json, f"internal error: {type(exc).__name__}: {exc}", 1)
        raise
