"""The ``condtrack`` command line: a Click group of thin commands, one module each (console script ``condtrack_cli.cli:main``).

Each command parses its options, calls the library and prints; no numerics here.
A command's module is imported only when that command runs or shows its help:
``condtrack --help`` and ``--version`` load neither the library nor numpy.
"""

from __future__ import annotations

import os
import sys
from importlib import import_module

import click

from condtrack_cli import __version__
from condtrack_cli.errors import CondtrackError
from condtrack_cli.interrupts import exit_code, raise_on_sigterm
from condtrack_cli.progress import show_warnings
from condtrack_cli.streams import QuietPipe

#: Command name -> (its object as ``module:attribute`` under condtrack_cli.cli, the first paragraph of its help).
#: The paragraph is what ``condtrack --help`` lists; a test keeps it equal to the command's own.
COMMANDS = {
    "compare": ("compare:compare_command", "Compare two track files A and B (.csv, .h5 or .hdf5, any combination)."),
    "eval": ("eval:eval_command",
             "Score PRED (a condtrack .csv or .h5) against the ground truth GT with the TAP-Vid metrics."),
    "info": ("info:info_command", "Print what the track file TRACKS (.h5 or .csv) holds: versions, input, points, config."),
    "render": ("render:render_command",
               "Draw the tracks of TRACKS (.h5 or .csv) on the frames of INPUT, the sequence they were tracked on."),
    "stages": ("stages:stages", "List the registered stages per kind (built-in and from entry points)."),
    "status": ("status:status_command",
               "Show what became of each input of the batch written into OUT_DIR (its manifest.jsonl)."),
    "synth": ("synth:synth", "Write a synthetic scene with exact ground truth: frames, queries.csv, tracks.csv, labels.csv."),
    "track": ("track:track", "Track points through INPUT, a folder of frames, a multi-page TIFF or a video file."),
}


class _Interrupted(Exception):
    """Ctrl-C or SIGTERM (its ``__cause__``) during a command, carried past Click, which would print a blank line first
    (it closes a terminal's ``^C`` echo; ``main`` prints it on a terminal only)."""


class LazyGroup(click.Group):
    """A group whose commands (``COMMANDS``) are imported on first use; its help lists them without importing any."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, _, attribute = COMMANDS[name][0].partition(":")
        return getattr(import_module(f"condtrack_cli.cli.{module}"), attribute)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        """No command: the help on stderr and exit 2, as Click 8.2 shows it (its NoArgsIsHelpError, whose message is
        the whole help, would reach ``main`` as an ``Error: Usage: ...`` block under a second usage line)."""
        if not args and not ctx.resilient_parsing:
            click.echo(ctx.get_help(), err=True)
            ctx.exit(2)
        return super().parse_args(ctx, args)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as interrupt:
            raise _Interrupted() from interrupt

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The Commands section, shortened as Click shortens a command's help, from ``COMMANDS``."""
        limit = formatter.width - 6 - max(map(len, COMMANDS))
        rows = [(name, click.Command(name, help=summary).get_short_help_str(limit))
                for name, (_, summary) in sorted(COMMANDS.items())]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="condtrack")
def cli() -> None:
    """Batch point tracking with conditional filters (Arnaud, Mémin & Cernuschi-Frías, RFIA 2004)."""
    show_warnings(True)  # every command's warnings as ``warning: ...`` lines (track -q silences them)


def main() -> None:
    """Console entry point: one-line ``Error: ...`` and a non-zero exit on bad input."""
    raise_on_sigterm()
    sys.stdout, sys.stderr = (stream and QuietPipe(stream) for stream in (sys.stdout, sys.stderr))
    # FFmpeg's own log lines ("moov atom not found") off, as OpenCV reads it on its first video open in the process
    # (batch workers inherit it); condtrack's error names the file. A level the user set is kept.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    try:
        code = cli.main(prog_name="condtrack", standalone_mode=False)
    except CondtrackError as error:
        click.echo(f"Error: {error}", err=True)
        sys.exit(error.exit_code)
    except (_Interrupted, click.exceptions.Abort, KeyboardInterrupt) as stop:  # Ctrl-C or SIGTERM (Abort: while parsing)
        interrupt = stop if isinstance(stop, KeyboardInterrupt) else stop.__cause__ or stop.__context__
        if isinstance(stop, _Interrupted) and _on_terminal():
            click.echo(err=True)  # past the terminal's ^C
        click.echo("Error: interrupted", err=True)
        sys.exit(exit_code(interrupt) if isinstance(interrupt, KeyboardInterrupt) else 130)
    except click.ClickException as error:  # a usage error (exit 2) shows the command's usage line first, as Click does
        if isinstance(error, click.UsageError) and error.ctx is not None:
            click.echo(error.ctx.get_usage(), err=True)
        click.echo(f"Error: {error.format_message()}", err=True)
        sys.exit(error.exit_code)
    sys.exit(code if isinstance(code, int) else 0)


def _on_terminal() -> bool:
    """Whether stderr is a terminal (False without a stream or on a closed one)."""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False
