"""``condtrack track INPUT...``: track one input (or a batch) into a track file; a thin layer over ``run``."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import click
from click.core import ParameterSource

from condtrack_cli import MAX_SEED, registry
from condtrack_cli.cli.batch_options import batch_options, refuse_batch_options
from condtrack_cli.cli.options import (FiniteFloatRange, checked, overlay_options, overlay_style, track_file_suffix,
                                       video_suffix)
from condtrack_cli.config import Config, config_keys, load_config
from condtrack_cli.errors import CondtrackError, read_error, warn
from condtrack_cli.io.atomic import refuse_overwriting_inputs
from condtrack_cli.io.formats import is_hdf5
from condtrack_cli.progress import Progress, show_warnings
from condtrack_cli.threads import requested_threads, threads_per_job, use_threads


class _MethodChoice(click.Choice):
    """``-m``: a choice among the registered tracking methods, read from the registry (entry points included) when needed."""

    def __init__(self) -> None:
        super().__init__(())

    @property
    def choices(self) -> tuple[str, ...]:
        return registry.tracking_methods()

    @choices.setter
    def choices(self, _value) -> None:
        """Click's constructor sets the choices; they are the registry's instead."""


def _complete_key(ctx: click.Context, param: click.Parameter, incomplete: str) -> list[str]:
    """Shell completion of --set: the config keys that start with what is typed."""
    return [key for key in config_keys() if key.startswith(incomplete)]


@click.command("track")
@click.argument("inputs", metavar="INPUT...", nargs=-1, type=click.Path(readable=False))  # a path, checked by the run
@click.option("-c", "--config", "config_path", type=click.Path(dir_okay=False), help="YAML config (default: configs/default.yaml's values).")
@click.option("-p", "--queries", "queries_path", type=click.Path(dir_okay=False), help="CSV of query points: frame,x,y[,point_id].")
@click.option("-m", "--method", type=_MethodChoice(), help="Tracking method (overrides filter.method); see `condtrack stages`.")
@click.option("-o", "--output", "output_path", type=click.Path(dir_okay=False, allow_dash=True),
              callback=checked(track_file_suffix, stdout="-"), help="Output .h5/.hdf5 or .csv (default, or -: CSV on stdout).")
@click.option("--overlay", "overlay_path", type=click.Path(dir_okay=False), callback=checked(video_suffix),
              help="Also render an overlay video (.mp4) of the tracks.")
@overlay_options
@click.option("--seed", type=click.IntRange(min=0, max=MAX_SEED), default=0, show_default=True,
              help="Seed of every random draw.")
@click.option("--max-std", type=FiniteFloatRange(min=0, min_open=True), metavar="PIXELS",
              help="Write a row as not visible when the std along its covariance's major axis exceeds PIXELS (output.max_std).")
@click.option("--forward-only", is_flag=True,
              help="Track each point from its query frame on only: no rows before it, no backward pass (output.backward=false).")
@click.option("--smooth", is_flag=True, help="Two-way smoothing: each frame's estimate also uses the later frames (filter.smooth).")
@click.option("--untrackable", type=click.Choice(["keep", "drop", "error"]),
              help="Queries whose Shi-Tomasi score is at or below detect.min_eigenvalue: keep (tracked, with a warning; "
                   "default), drop (not tracked) or error (detect.untrackable).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", shell_complete=_complete_key, help="Override one config value, e.g. measure.template=15 (repeatable).")
@click.option("--from-list", "list_path", type=click.Path(dir_okay=False), help="Batch: a file with one INPUT per line.")
@click.option("--out-dir", type=click.Path(file_okay=False), help="Batch: folder of the outputs (created if missing), one <input name>.<format> each, and manifest.jsonl.")
@click.option("--format", "batch_format", type=click.Choice(["h5", "csv"]), default="h5", show_default=True, help="Batch: output format.")
@click.option("-j", "--jobs", type=click.IntRange(min=1), help="Batch: inputs processed in parallel (default 1; not with --scheduler).")
@batch_options
@click.option("-q", "--quiet", is_flag=True,
              help="No progress bar, summary or warnings on stderr (a batch still prints its failed inputs).")
def track(inputs, config_path, queries_path, method, output_path, overlay_path, overlay_points, ellipses, ellipse_cap,
          seed, max_std, forward_only, smooth, untrackable, overrides, list_path, out_dir, batch_format, jobs, quiet, threads,
          **batch) -> None:
    """Track points through INPUT, a folder of frames, a multi-page TIFF or a video file.

    Several INPUTs (or --from-list) make a batch: one output per input in
    --out-dir, a failing input is reported and the others go on, a final table
    gives each input's status, and the exit code is 1 if any input failed.
    OUT_DIR/manifest.jsonl gets one line per input as it ends.
    """
    from condtrack_cli.run import track_input

    show_warnings(not quiet)
    usage = click.get_current_context()
    style = overlay_style(overlay_points, ellipses, ellipse_cap, overlay_path)
    inputs = list(inputs) + (_read_list(list_path) if list_path else [])
    if not inputs:
        usage.fail(f"{list_path}: no input listed (only blank lines and # comments)" if list_path
                   else "no INPUT given (a frame folder, a multi-page TIFF or a video file, or --from-list FILE)")
    in_batch = len(inputs) > 1 or out_dir is not None
    if in_batch and (output_path or overlay_path):
        usage.fail("-o and --overlay take one input; a batch writes into --out-dir")
    if in_batch and out_dir is None:
        usage.fail("several inputs need --out-dir")
    if output_path == "-":  # stdout, as without -o
        output_path = None
    if not in_batch:
        refuse_batch_options({**batch, "jobs": jobs,
                              "format": usage.get_parameter_source("batch_format") is ParameterSource.COMMANDLINE})
    options = {name: override for name, override, given in (
        ("--smooth", "filter.smooth=true", smooth), ("--untrackable", f"detect.untrackable={untrackable}", untrackable),
        ("--max-std", f"output.max_std={max_std!r}", max_std is not None),
        ("--forward-only", "output.backward=false", forward_only)) if given}
    csv_output = batch_format == "csv" if in_batch else output_path is None or not is_hdf5(output_path)
    config: Config = load_config(config_path, list(overrides), method, options, csv_output)
    if not in_batch:
        threads, warning = threads_per_job(requested_threads(threads), 1)
        if warning:
            warn(warning)
        use_threads(threads)
        refuse_overwriting_inputs({"-o": output_path, "--overlay": overlay_path},
                                  {"INPUT": inputs[0], "-p": queries_path, "-c": config_path})
        with contextlib.nullcontext() if quiet else Progress() as progress:
            summary = track_input(inputs[0], config, queries_path, output_path, seed, progress, overlay_path, style)
        if not quiet:
            click.echo(summary.line(config.method), err=True)
        return
    from condtrack_cli.batch import run_batch  # here only: one input does not import the batch machinery

    run_batch(inputs, config, queries_path, out_dir, batch_format, seed, jobs, quiet, threads=threads, **batch)


def _read_list(path: str) -> list[str]:
    """The inputs of a --from-list file, one a line (blank lines and # comments skipped), relative to its folder (to
    the working directory for a pipe: ``--from-list <(ls -d clips/*)``, /dev/stdin)."""
    try:
        lines = Path(path).read_text(encoding="utf-8-sig").splitlines()  # -sig: a Windows editor's byte-order mark
    except OSError as error:
        raise read_error(error, f"{path}: cannot read the input list ({error.strerror})") from None
    except UnicodeDecodeError as error:
        raise CondtrackError(f"{path}: the input list is not UTF-8 text (byte {error.object[error.start]:#04x} at "
                             f"offset {error.start})") from None
    folder = os.path.dirname(path) if os.path.isfile(path) else ""  # a pipe's /dev/fd/63: not the inputs' folder
    return [os.path.join(folder, line.strip()) for line in lines if line.strip() and not line.lstrip().startswith("#")]
