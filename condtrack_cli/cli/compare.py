"""``condtrack compare A B``: do two track files agree, within tolerances? (golden files in CI)

Exit status: 0 when they agree, 1 when they differ, 2 when a file cannot be
read (missing, damaged, not a condtrack file, unknown schema) or on bad usage.
"""

from __future__ import annotations

import json
import math

import click

from condtrack_cli.errors import CondtrackError
from condtrack_cli.io.formats import is_hdf5
from condtrack_cli.io.compare import (
    ATOL_PX, COV_ATOL, CSV_FIELDS, HDF5_FIELDS, RTOL_COV, Comparison, compare_tracks,
)

#: Exit status per outcome.
AGREE, DIFFER, UNREADABLE = 0, 1, 2


def _value(value: float | int | str | None) -> str:
    """One value for the plain report: floats with 10 significant digits."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.10g}"
    return str(value)


def _json_value(value: float | int | str | None) -> float | int | str | None:
    """A value for strict JSON: a non-finite float as the string "inf", "-inf" or "nan"."""
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def report_lines(result: Comparison, path_a: str, path_b: str) -> list[str]:
    """The plain report: verdict, differing counts per field, then the largest differences."""
    verdict = "agree" if result.agree else "differ"
    lines = [
        f"{verdict}: A={path_a} B={path_b} ({result.n_points} points, {result.n_frames} frames; "
        f"atol {result.atol_px:g} px, cov rtol {result.rtol_cov:g}, {result.visible_flips} visibility flips allowed)"
    ]
    skipped = [name for name in HDF5_FIELDS if name not in result.fields]
    if skipped:
        lines.append(f"not compared (a CSV does not hold them): {', '.join(skipped)}")
    allowed = " (allowed)" if result.counts.get("visible", 0) <= result.visible_flips else ""
    counted = [f"{name} {count}" + (allowed if name == "visible" else "") for name, count in result.counts.items() if count]
    if counted:
        lines.append("differing values: " + ", ".join(counted))
    if result.top:
        lines.append("largest differences:")
        rows = [("point", "frame", "field", "A", "B", "|A-B|")] + [
            (_value(d.point_id), _value(d.frame), d.field, _value(d.a), _value(d.b),
             "-" if d.diff is None else f"{d.diff:.3g}")
            for d in result.top
        ]
        widths = [max(len(row[i]) for row in rows) for i in range(6)]
        for row in rows:
            cells = [cell.ljust(w) if i == 2 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths))]
            lines.append("  " + "  ".join(cells).rstrip())
    return lines


def report_json(result: Comparison, path_a: str, path_b: str) -> dict:
    """The ``--json`` report as a JSON-ready dict (non-finite values as strings)."""
    return {
        "agree": result.agree, "a": path_a, "b": path_b,
        "n_points": result.n_points, "n_frames": result.n_frames, "fields": list(result.fields),
        "tolerances": {"atol_px": result.atol_px, "rtol_cov": result.rtol_cov, "atol_cov": COV_ATOL,
                       "visible_flips": result.visible_flips},
        "counts": result.counts,
        "top": [
            {"point_id": d.point_id, "frame": d.frame, "field": d.field,
             "a": _json_value(d.a), "b": _json_value(d.b), "diff": d.diff}
            for d in result.top
        ],
    }


class FiniteFloat(click.ParamType):
    """A finite float >= 0 (nan would make every comparison pass; inf is no tolerance, say so by a large number)."""

    name = "float"

    def convert(self, value, param, ctx) -> float:
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(number) or number < 0:
            self.fail(f"{value!r} is not a finite number >= 0", param, ctx)
        return number


@click.argument("path_a", metavar="A")
@click.argument("path_b", metavar="B")
@click.option("--atol-px", type=FiniteFloat(), default=ATOL_PX, show_default=True,
              help="Absolute tolerance on positions, query positions and measurements (px).")
@click.option("--rtol-cov", type=FiniteFloat(), default=RTOL_COV, show_default=True,
              help=f"Relative tolerance on covariances (plus {COV_ATOL:g} px^2).")
@click.option("--ignore-visible-flips", "visible_flips", type=click.IntRange(min=0), default=0, show_default=True,
              metavar="N", help="Number of (point, frame) visibility flips still counted as agreement.")
@click.option("--top", type=click.IntRange(min=0), default=10, show_default=True, help="Differences listed.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of the plain report.")
@click.pass_context
def _compare(ctx: click.Context, path_a: str, path_b: str, atol_px: float, rtol_cov: float, visible_flips: int,
             top: int, as_json: bool) -> None:
    """Compare two track files A and B (.csv, .h5 or .hdf5, any combination).

    \b
    Points are matched by point_id, frames by index. Compared per point and
    frame where both have a position: x, y (--atol-px), the covariance
    entries (--rtol-cov), visible (--ignore-visible-flips) and method; a
    position in one file only, a point in one file only, and (HDF5 against
    HDF5) the queries, the frame count, cov_yx and the measurements z and R.
    A CSV holds no queries or measurements: those are compared only between
    two HDF5 files. inf equals only inf of the same sign, nan only nan.

    Exit status: 0 agree, 1 differ, 2 unreadable file.
    """
    from condtrack_cli.io.read import read_tracks

    try:
        a, _ = read_tracks(path_a)
        b, _ = read_tracks(path_b)
    except CondtrackError as error:
        click.echo(f"Error: {error}", err=True)
        ctx.exit(UNREADABLE)
    both_hdf5 = is_hdf5(path_a) and is_hdf5(path_b)
    fields = HDF5_FIELDS if both_hdf5 else CSV_FIELDS
    result = compare_tracks(a, b, atol_px, rtol_cov, visible_flips, fields=fields, top=top)
    if as_json:
        click.echo(json.dumps(report_json(result, path_a, path_b)))
    else:
        click.echo("\n".join(report_lines(result, path_a, path_b)))
    ctx.exit(AGREE if result.agree else DIFFER)


compare_command = click.command("compare")(_compare)
