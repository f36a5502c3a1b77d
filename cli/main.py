"""Entry point of the `zoo` command.

Every command raises :class:`zoo.errors.ZooError` for bad input; :func:`main` turns it into
one line on stderr and a non-zero exit, with the traceback only under ``--debug``.
"""

from __future__ import annotations

import sys

import typer

from zoo.errors import ZooError

# rich_markup_mode=None: help texts print as written; under rich markup "[sim]" or "NAME[@VERSION]" vanished as tags.
app = typer.Typer(no_args_is_help=True, add_completion=False, rich_markup_mode=None,
                  help="Neural SDFs and amortized collision detection.")


@app.callback()
def _options(debug: bool = typer.Option(False, "--debug", help="Show full tracebacks on errors.")):
    """Declares ``--debug`` for the help text; :func:`main` reads it from argv before typer runs."""


def register_commands() -> None:
    """Import the modules that add commands to ``app`` (kept in one place so the list reads as the CLI)."""
    from . import bench, commands, fit, models, sim  # noqa: F401


def main(argv: list[str] | None = None) -> None:
    register_commands()
    debug = "--debug" in (argv if argv is not None else sys.argv[1:])
    try:
        code = app(args=argv, standalone_mode=False)  # a command's typer.Exit(n) comes back as n here, not raised
        if isinstance(code, int) and not isinstance(code, bool) and code:
            sys.exit(code)
    except ZooError as exc:
        if debug:
            raise
        typer.secho(f"error: {exc}", fg="red", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        typer.secho("interrupted; rerun the same command to resume", fg="yellow", err=True)
        sys.exit(130)
    except Exception as exc:  # click's own usage errors come through here too
        import click

        if isinstance(exc, click.exceptions.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        if isinstance(exc, click.exceptions.Abort):
            sys.exit(1)
        if debug:
            raise
        typer.secho(f"error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)", fg="red", err=True)
        sys.exit(1)


if __name__ == "__main__":  # pragma: no cover - `python -m sdfzoo.cli.main`: run the imported module's app,
    from sdfzoo.cli.main import main as imported_main  # on which the command modules register (not this __main__'s)

    imported_main()
