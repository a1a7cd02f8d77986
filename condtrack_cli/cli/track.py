"""The ``condtrack`` command line: a thin Click layer over the library (no numerics here)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import click
import numpy as np

from condtrack_cli import __version__, registry
from condtrack_cli.config import Config, default_yaml, load_config
from condtrack_cli.errors import CondtrackError


class _Progress:
    """Per-frame progress on stderr: a rich bar on a terminal, a plain line every tenth otherwise."""

    def __init__(self, n_frames: int):
        self.n_frames, self.done = n_frames, 0
        self.step = max(1, n_frames // 10)
        self.bar = None
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[active]} active"),
                TimeRemainingColumn(), console=Console(stderr=True), transient=True,
            )
            self.task = self.bar.add_task("track", total=n_frames, active=0)
            self.bar.start()

    def __call__(self, index: int, estimate) -> None:
        self.done += 1
        active = int(np.isfinite(estimate.xy[:, 0]).sum())
        if self.bar is not None:
            self.bar.update(self.task, completed=self.done, active=active)
        elif self.done % self.step == 0 or self.done == self.n_frames:
            click.echo(f"frame {self.done}/{self.n_frames}: {active} active points", err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _configure_logging(quiet: bool) -> None:
    """Warnings of the library go to stderr as ``warning: ...`` lines, unless quiet."""
    logger = logging.getLogger("condtrack")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("warning: %(message)s"))
        logger.addHandler(handler)
        logger.propagate = False
    logger.setLevel(logging.ERROR if quiet else logging.WARNING)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="condtrack")
def cli() -> None:
    """Batch point tracking with conditional filters (Arnaud, Mémin & Cernuschi-Frías, RFIA 2004)."""


@cli.command()
@click.argument("inputs", metavar="INPUT...", nargs=-1)
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), help="YAML config (default: configs/default.yaml's values).")
@click.option("-p", "--queries", "queries_path", type=click.Path(dir_okay=False), help="CSV of query points: frame,x,y[,point_id].")
@click.option("-m", "--method", help="Tracking method (overrides filter.method); see `condtrack stages`.")
@click.option("-o", "--output", "output_path", type=click.Path(dir_okay=False), help="Output .h5/.hdf5 or .csv (default: CSV on stdout).")
@click.option("--overlay", "overlay_path", type=click.Path(dir_okay=False), help="Also render an overlay video (.mp4) of the tracks.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Override one config value, e.g. motion.levels=3 (repeatable).")
@click.option("--from-list", "list_path", type=click.Path(dir_okay=False), help="Batch: a file with one INPUT per line.")
@click.option("--out-dir", type=click.Path(file_okay=False), help="Batch: folder of the outputs, one <input name>.<format> each.")
@click.option("--format", "batch_format", type=click.Choice(["h5", "csv"]), default="h5", show_default=True, help="Batch: output format.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=1, show_default=True, help="Batch: inputs processed in parallel.")
@click.option("-q", "--quiet", is_flag=True, help="No progress or summary on stderr.")
def track(inputs, config_path, queries_path, method, output_path, overlay_path, seed, overrides, list_path, out_dir,
          batch_format, jobs, quiet) -> None:
    """Track points through INPUT, a folder of frames or a video file.

    Several INPUTs (or --from-list) make a batch: one output per input in
    --out-dir, a failing input is reported and the others go on, a final table
    gives each input's status, and the exit code is 1 if any input failed.
    """
    from condtrack_cli.run import track_batch, track_input

    _configure_logging(quiet)
    inputs = list(inputs) + (_read_list(list_path) if list_path else [])
    if not inputs:
        raise CondtrackError("no INPUT given (a frame folder or a video file, or --from-list FILE)")
    config: Config = load_config(config_path, list(overrides), method)
    if len(inputs) == 1 and out_dir is None:
        progress = None if quiet else _Progress
        summary = track_input(inputs[0], config, queries_path, output_path, seed, progress, overlay_path)
        if not quiet:
            click.echo(summary.line(config.method), err=True)
        return
    if output_path or overlay_path:
        raise CondtrackError("-o and --overlay take one input; a batch writes into --out-dir")
    if out_dir is None:
        raise CondtrackError("several inputs need --out-dir")
    summaries = track_batch(inputs, config, queries_path, Path(out_dir), f".{batch_format}", seed, jobs)
    _print_batch_table(summaries, config.method)
    if any(s.error for s in summaries):
        sys.exit(1)


def _read_list(path: str) -> list[str]:
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except OSError as error:
        raise CondtrackError(f"{path}: cannot read the input list ({error.strerror})") from None
    return [line.strip() for line in lines if line.strip() and not line.lstrip().startswith("#")]


def _print_batch_table(summaries, method: str) -> None:
    """The batch's final table, on stderr (stdout stays clean)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"condtrack batch ({method})")
    for column in ("input", "status", "points", "visible", "s/frame", "output or error"):
        table.add_column(column)
    for s in summaries:
        if s.error:
            table.add_row(s.input, "failed", "", "", "", s.error)
        else:
            table.add_row(s.input, "ok", str(s.n_points), f"{s.visible_share:.1%}", f"{s.seconds_per_frame:.3f}", s.output)
    Console(stderr=True, width=160).print(table)


@cli.command()
@click.option("--default-config", is_flag=True, help="Print the default configuration as commented YAML.")
def stages(default_config: bool) -> None:
    """List the registered stages per kind (built-in and from entry points)."""
    if default_config:
        click.echo(default_yaml(), nl=False)
        return
    for kind in registry.KINDS:
        click.echo(f"{kind}:")
        for name in registry.names(kind):
            click.echo(f"  {name:12s} {registry.get(kind, name).summary}")


@cli.command()
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--scene", help="Scene to write into OUT: camera_motion, occlusion, ring, illumination, fast.")
@click.option("--samples", is_flag=True, help="Write the shipped sample sequences under OUT instead (make samples).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--size", default="320x240", show_default=True, help="WIDTHxHEIGHT in pixels.")
@click.option("--frames", "n_frames", type=click.IntRange(min=2), help="Number of frames (the scene's default otherwise).")
@click.option("--noise", type=click.FloatRange(min=0), help="Noise standard deviation (grey levels).")
def synth(out, scene, samples, seed, size, n_frames, noise) -> None:
    """Write a synthetic scene with exact ground truth: frames, queries.csv, tracks.csv, labels.csv."""
    from condtrack_cli.frames.synthetic import make_scene, write_samples, write_scene

    if samples:
        for name, folder in write_samples(out).items():
            click.echo(f"{name}: {folder}")
        return
    if not scene:
        raise CondtrackError("synth needs --scene NAME or --samples")
    width, sep, height = size.partition("x")
    if not (sep and width.isdigit() and height.isdigit()):
        raise CondtrackError(f"--size: expected WIDTHxHEIGHT, got {size!r}")
    try:
        written = write_scene(make_scene(scene, seed, (int(width), int(height)), n_frames, noise), out)
    except ValueError as error:
        raise CondtrackError(str(error)) from None
    click.echo(f"{scene}: {written}")


def _add_commands() -> None:
    from condtrack_cli.cli.eval import eval_command
    from condtrack_cli.cli.compare import compare_command
    from condtrack_cli.cli.render import info_command, render_command

    for command in (eval_command, compare_command, render_command, info_command):
        cli.add_command(command)


_add_commands()


def main() -> None:
    """Console entry point: one-line ``Error: ...`` and a non-zero exit on bad input."""
    try:
        code = cli.main(standalone_mode=False)
    except CondtrackError as error:
        click.echo(f"Error: {error}", err=True)
        sys.exit(1)
    except click.exceptions.Abort:
        click.echo("Error: interrupted", err=True)
        sys.exit(130)
    except KeyboardInterrupt:
        click.echo("Error: interrupted", err=True)
        sys.exit(130)
    except click.ClickException as error:
        click.echo(f"Error: {error.format_message()}", err=True)
        sys.exit(error.exit_code)
    sys.exit(code if isinstance(code, int) else 0)
