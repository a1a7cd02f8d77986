"""``condtrack eval PRED GT``: score a condtrack output against ground truth (TAP-Vid metrics)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from condtrack_cli.cli.options import checked, json_value, png_suffix
from condtrack_cli.evaluate.groundtruth import load_gt_csv, load_gt_tapvid
from condtrack_cli.evaluate.metrics import METRIC_KEYS, QUERY_MODES
from condtrack_cli.evaluate.score import score_tracks

_GT_READERS = {"csv": load_gt_csv, "tapvid": load_gt_tapvid}


def _format(key: str, value: float | int | None) -> str:
    """One metric for the table: fractions as percentages, pixels with 2 decimals, counts as ints."""
    if value is None:
        return "n/a"
    if key in ("n_points", "n_frames"):
        return str(value)
    if key == "median_err":
        return f"{value:.2f} px"
    if key == "nees":
        return f"{value:.2f}"
    return f"{100 * value:.1f} %"


def _print_table(result: dict, notes: list[str], title: str) -> None:
    """The title line, the metrics as a rich table, then the notes, on stdout."""
    from rich.console import Console
    from rich.table import Table

    table = Table()
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in METRIC_KEYS:
        table.add_row(key, _format(key, result[key]))
    console = Console(highlight=False)
    console.print(title, markup=False)
    console.print(table)
    for note in notes:
        console.print(note, markup=False)


@click.command("eval")
@click.argument("pred", type=click.Path(dir_okay=False))
@click.argument("gt", type=click.Path(dir_okay=False))
@click.option("--query-mode", type=click.Choice(QUERY_MODES), default="first", show_default=True,
              help="first: score the frames after each point's query frame; strided: every frame but it.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table (strict JSON: an infinite value is the string \"inf\").")
@click.option("--gt-format", type=click.Choice(tuple(_GT_READERS)), default="csv", show_default=True,
              help="csv: point_id,frame,x,y,visible; tapvid: a TAP-Vid pickle holding one video (arrays, dicts, "
                   "lists and numbers only: a pickle naming other code is refused).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False), default=None, metavar="FILE.png",
              callback=checked(png_suffix),
              help="Also draw the reliability diagram and the normalised-error histogram (needs condtrack[plot]).")
@click.option("--queries", "queries_path", type=click.Path(dir_okay=False), default=None, metavar="FILE",
              help="The queries CSV PRED was tracked from (track -p): each point's query frame and position, matched "
                   "by point_id; an HDF5 PRED's stored queries must agree with it.")
def eval_command(pred: str, gt: str, query_mode: str, as_json: bool, gt_format: str, plot_path: str | None,
                 queries_path: str | None) -> None:
    """Score PRED (a condtrack .csv or .h5) against the ground truth GT with the TAP-Vid metrics.

    \b
    Metrics (TAP-Vid, Doersch et al. 2022, in pixels of the sequence):
      pts_within_x  fraction of GT-visible scored frames predicted strictly
                    closer than x px (x = 1, 2, 4, 8, 16); delta_avg: their mean
      jaccard_x     TP / (GT visible + FP); AJ: their mean
      OA            fraction of scored frames with the right visibility
      median_err    median distance on GT-visible scored frames (px); a frame
                    without a position counts as infinitely far, so n/a (null)
                    when more than half of them have none
      covP          fraction of GT-visible scored positions inside the
                    predicted ellipse of level P% (P = 50, 90, 95, 99; ideal P/100)
      nees          mean d^T C^-1 d over those with a finite covariance (ideal 2;
                    inf when one is beyond the float range)
      cov_finite    fraction of GT-visible scored positions with a finite covariance
      cov50_rescaled  cov50 after scaling every covariance by the one factor
                    that puts cov95 at 0.95 (0.5: only the scale is off; above:
                    the errors are heavier-tailed than the covariances)
    --plot FILE.png draws the coverage at every level against the level (a
    calibrated covariance follows the diagonal) and the histogram of the
    Mahalanobis distances of the errors against the calibrated (Rayleigh) law.
    A point's query frame is the file's query (HDF5) or its first row (CSV);
    --queries FILE (the `track -p` file) gives a CSV's points their query frames and
    positions, so it scores as the HDF5 of the same run. GT CSV rows that are
    absent are not scored. OA, AJ and jaccard_x are n/a (null) when the GT has
    no occluded scored frame: there is then no visibility to judge; a metric of
    GT-visible scored frames (delta_avg, covP, ...) is n/a when there is none. Points are
    matched by point_id; GT points missing from PRED, and points of PRED missing
    from GT, are not scored (their counts are reported, on stderr with --json). Frames where PRED has no position count
    as not visible and not within any threshold. Each point's query must lie
    within 1 px of the GT on its query frame where the GT has it visible, else
    PRED is refused (tracked from other queries, e.g. detected without -p); a
    CSV without --queries passes where any row of the point lies within
    1 px of its GT (its first row is frame 0 after the backward pass, not the
    query, and is scored from there: the HDF5 output scores from the query).
    """
    from condtrack_cli.io.atomic import refuse_overwriting_inputs
    from condtrack_cli.io.formats import track_format
    from condtrack_cli.io.read import read_tracks

    truth = _GT_READERS[gt_format](gt)
    refuse_overwriting_inputs({"--plot": plot_path}, {"of GT": _frame_folder(Path(gt).parent, truth.gt_xy.shape[1])})
    tracks, _ = read_tracks(pred)
    result, data = score_tracks(tracks, truth, query_mode, from_csv=track_format(pred) == "csv", queries=queries_path)
    if plot_path is not None:
        from condtrack_cli.evaluate.plot import write_plot

        write_plot(data, query_mode, plot_path, f"{pred}, '{query_mode}' query mode")
    notes = []
    if len(data.missing_ids):
        notes.append(f"note: {len(data.missing_ids)} GT point(s) missing from {pred}, not scored: "
                     f"{_first_ids(data.missing_ids)}")
    if len(data.unscored_ids):
        notes.append(f"note: {len(data.unscored_ids)} point(s) of {pred} not in the GT, not scored: "
                     f"{_first_ids(data.unscored_ids)}")
    if truth.gt_xy.shape[1] > tracks.xy.shape[1]:
        notes.append(
            f"note: the GT has {truth.gt_xy.shape[1]} frames, {pred} only {tracks.xy.shape[1]}; "
            "the GT frames beyond count as not predicted"
        )
    if as_json:
        click.echo(json.dumps(json_value(result), allow_nan=False))
        for note in notes:
            click.echo(note, err=True)
    else:
        _print_table(result, notes, f"{pred} vs {gt}, '{query_mode}' query mode")


def _first_ids(ids) -> str:
    """The first ten point ids of ``ids`` for a note, ``...`` after them when there are more."""
    return ", ".join(str(i) for i in ids[:10]) + (", ..." if len(ids) > 10 else "")


def _frame_folder(folder: Path, frames: int) -> Path | None:
    """``folder`` where it holds at least ``frames`` image files, the GT's frame count (GT's folder is then the
    sequence's frame folder: a picture written there would replace or add a frame), else None: a working folder that
    holds the GT CSV and an earlier plot or two is not one."""
    from condtrack_cli.frames.readers import IMAGE_EXTENSIONS  # here: the readers load OpenCV

    if folder.is_dir() and sum(path.suffix.lower() in IMAGE_EXTENSIONS for path in folder.iterdir()) >= frames:
        return folder
    return None
