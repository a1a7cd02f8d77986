"""The ``condtrack`` command line: a Click group of thin commands, one module each (console script ``condtrack_cli.cli:main``).

Each command parses its options, calls the library and prints; no numerics here.
"""

from __future__ import annotations

import sys

import click

from condtrack_cli import __version__
from condtrack_cli.cli.compare import compare_command
from condtrack_cli.cli.eval import eval_command
from condtrack_cli.cli.info import info_command
from condtrack_cli.cli.render import render_command
from condtrack_cli.cli.stages import stages
from condtrack_cli.cli.synth import synth
from condtrack_cli.cli.track import track
from condtrack_cli.errors import CondtrackError
from condtrack_cli.interrupts import exit_code, raise_on_sigterm
from condtrack_cli.progress import show_warnings


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="condtrack")
def cli() -> None:
    """Batch point tracking with conditional filters (Arnaud, Mémin & Cernuschi-Frías, RFIA 2004)."""
    show_warnings(True)  # every command's warnings as ``warning: ...`` lines (track -q silences them)


for _command in (track, eval_command, compare_command, render_command, info_command, synth, stages):
    cli.add_command(_command)


def main() -> None:
    """Console entry point: one-line ``Error: ...`` and a non-zero exit on bad input."""
    raise_on_sigterm()
    try:
        code = cli.main(standalone_mode=False)
    except CondtrackError as error:
        click.echo(f"Error: {error}", err=True)
        sys.exit(error.exit_code)
    except (click.exceptions.Abort, KeyboardInterrupt) as stop:  # Ctrl-C or SIGTERM; Click turns them into Abort
        interrupt = stop if isinstance(stop, KeyboardInterrupt) else stop.__context__
        click.echo("Error: interrupted", err=True)
        sys.exit(exit_code(interrupt) if isinstance(interrupt, KeyboardInterrupt) else 130)
    except click.ClickException as error:
        click.echo(f"Error: {error.format_message()}", err=True)
        sys.exit(error.exit_code)
    sys.exit(code if isinstance(code, int) else 0)
