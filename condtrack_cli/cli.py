"""The ``condtrack`` command line: a thin Click layer over the library (no numerics here)."""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path

import click
import numpy as np

from condtrack_cli import __version__, registry
from condtrack_cli.config import Config, default_yaml, load_config
from condtrack_cli.errors import CondtrackError


def _check_output_path(path: Path) -> None:
    """Refuse an output path before any work: unknown extension, missing or read-only folder."""
    from condtrack_cli.output.write import writer_for

    writer_for(path)
    folder = path.parent
    if not folder.is_dir():
        raise CondtrackError(f"{path}: the output folder '{folder}' does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CondtrackError(f"{path}: the output folder '{folder}' is not writable")


class _Progress:
    """Per-frame progress on stderr: a rich bar on a terminal, plain lines otherwise, nothing when quiet."""

    def __init__(self, n_frames: int, quiet: bool):
        self.n_frames, self.quiet = n_frames, quiet
        self.started = time.perf_counter()
        self.bar = None
        if not quiet and sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[active]} active"),
                TimeRemainingColumn(), console=__import__("rich.console").console.Console(stderr=True), transient=True,
            )
            self.task = self.bar.add_task("track", total=n_frames, active=0)
            self.bar.start()
        self.step = max(1, n_frames // 10)
        self.done = 0

    def __call__(self, index: int, estimate) -> None:
        self.done += 1
        active = int(np.isfinite(estimate.xy[:, 0]).sum())
        if self.bar is not None:
            self.bar.update(self.task, completed=self.done, active=active)
        elif not self.quiet and (self.done % self.step == 0 or self.done == self.n_frames):
            click.echo(f"frame {self.done}/{self.n_frames}: {active} active points", err=True)

    def close(self) -> float:
        if self.bar is not None:
            self.bar.stop()
        return time.perf_counter() - self.started


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
@click.argument("input_path", metavar="INPUT")
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), help="YAML config (default: configs/default.yaml's values).")
@click.option("-p", "--queries", "queries_path", type=click.Path(dir_okay=False), help="CSV of query points: frame,x,y[,point_id].")
@click.option("-m", "--method", help="Tracking method (overrides filter.method); see `condtrack stages`.")
@click.option("-o", "--output", "output_path", type=click.Path(dir_okay=False), help="Output .h5/.hdf5 or .csv (default: CSV on stdout).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of every random draw.")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help="Override one config value, e.g. motion.levels=3 (repeatable).")
@click.option("-q", "--quiet", is_flag=True, help="No progress or summary on stderr.")
def track(input_path, config_path, queries_path, method, output_path, seed, overrides, quiet) -> None:
    """Track points through INPUT, a folder of frames or a video file."""
    from condtrack_cli import pipeline
    from condtrack_cli.output import write_tracks
    from condtrack_cli.output.write import csv_text
    from condtrack_cli.queries import read_queries

    _configure_logging(quiet)
    config: Config = load_config(config_path, list(overrides), method)
    if output_path is not None:
        _check_output_path(Path(output_path))
    frames_stage = config.stage("frames")
    source = registry.get("frames", frames_stage.name).factory(frames_stage.settings, input_path)
    info = source.info
    queries = read_queries(queries_path, info) if queries_path else None
    backward_frames = int(queries.frame.max()) + 1 if queries is not None and queries.frame.max() > 0 else 0
    progress = _Progress(info.n_frames + backward_frames, quiet)
    try:
        tracks = pipeline.run(source, info, config, queries, seed=seed, on_frame=progress)
    finally:
        seconds = progress.close()
    meta = {"config": config.to_yaml(), "method": config.method, "seed": seed}
    if output_path is None:
        sys.stdout.write(csv_text(tracks))
    else:
        write_tracks(tracks, output_path, info, meta, config.output)
    if not quiet:
        started = tracks.has_state
        share = tracks.visible[started].mean() if started.any() else 0.0
        where = f" -> {output_path}" if output_path else ""
        click.echo(
            f"{len(tracks.queries)} points, {share:.1%} of tracked rows visible, "
            f"{seconds / max(info.n_frames, 1):.3f} s/frame ({config.method}){where}", err=True,
        )


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


def _add_commands() -> None:
    from condtrack_cli.evaluate.command import eval_command

    cli.add_command(eval_command)


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
