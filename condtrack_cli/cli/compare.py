"""``condtrack compare A B``: do two track files agree, within tolerances? (golden files in CI)

Exit status: 0 when they agree, 1 when they differ, 2 when a file cannot be
read (missing, damaged, not a condtrack file, unknown schema) or on bad usage.
"""

from __future__ import annotations

import json

import click

from condtrack_cli.cli.options import FiniteFloatRange, json_value
from condtrack_cli.errors import CondtrackError
from condtrack_cli.io.formats import is_hdf5
from condtrack_cli.io.compare import (
    CSV_FIELDS, HDF5_FIELDS, STRICT, TOLERANT, Comparison, Tolerances, compare_tracks, with_options,
)

#: Exit status per outcome.
AGREE, DIFFER, UNREADABLE = 0, 1, 2


def _value(value: float | int | str | list | None) -> str:
    """One value for the plain report: floats with 10 significant digits, a vector or matrix comma-joined."""
    if value is None:
        return "-"
    if isinstance(value, list):
        return ",".join(f"{v:.6g}" for v in value)
    if isinstance(value, float):
        return f"{value:.10g}"
    return str(value)


def tolerance_line(tolerances: Tolerances) -> str:
    """What counts as the same result, in words."""
    t = tolerances
    if t.max_share == 0:
        cells = "no cell beyond them"
    else:
        cells = (f"at most {t.max_share * 100:g}% of cells beyond them, "
                 f"none beyond {t.max_px:g} px where both see the point")
    flips = f"{t.visible_flips} visibility flips allowed" + (" beyond near-ties" if t.near_ties else "")
    return f"tolerances: positions {t.atol_px:g} px, covariances and dof {t.rtol_cov:g} relative, {cells}; {flips}"


def report_lines(result: Comparison, path_a: str, path_b: str) -> list[str]:
    """The plain report: verdict, tolerances, differing cells, counts per field, then the largest differences."""
    verdict = "agree" if result.agree else "differ"
    lines = [
        f"{verdict}: A={path_a} B={path_b} ({result.n_points} points, {result.n_frames} frames)",
        tolerance_line(result.tolerances),
    ]
    skipped = [name for name in HDF5_FIELDS if name not in result.fields]
    if skipped:
        lines.append(f"not compared (a CSV does not hold them): {', '.join(skipped)}")
    share = result.differing_cells / result.cells * 100 if result.cells else 0.0
    lines.append(f"differing cells: {result.differing_cells} of {result.cells} ({share:.2f}%); "
                 f"largest position difference {result.max_px:.3g} px"
                 + (f" ({result.max_px_seen:.3g} px where both see the point)"
                    if result.max_px_seen != result.max_px else ""))
    ties = f" ({result.ties} near-tie{'s' if result.ties > 1 else ''})" if result.ties else ""
    counted = [f"{name} {count}" + (ties if name == "visible" else "") for name, count in result.counts.items() if count]
    if counted:
        lines.append("differing values: " + ", ".join(counted))
    if result.top:
        lines.append("largest differences:")
        rows = [("point", "frame", "field", "A", "B", "diff")] + [
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
    """The ``--json`` report as a JSON-ready dict (non-finite values as strings: --strict's ``max_px`` is "inf")."""
    t = result.tolerances
    return json_value({
        "agree": result.agree, "a": path_a, "b": path_b,
        "n_points": result.n_points, "n_frames": result.n_frames, "fields": list(result.fields),
        "tolerances": {"atol_px": t.atol_px, "rtol_cov": t.rtol_cov, "max_share": t.max_share, "max_px": t.max_px,
                       "visible_flips": t.visible_flips, "near_ties": t.near_ties},
        "cells": result.cells, "differing_cells": result.differing_cells, "max_px": result.max_px,
        "max_px_seen": result.max_px_seen,
        "near_ties": result.ties, "counts": result.counts,
        "top": [
            {"point_id": d.point_id, "frame": d.frame, "field": d.field,
             "a": d.a, "b": d.b, "diff": d.diff}
            for d in result.top
        ],
    })


@click.argument("path_a", metavar="A")
@click.argument("path_b", metavar="B")
@click.option("--atol-px", type=FiniteFloatRange(min=0), default=None,
              help=f"A cell differs where its positions are farther apart (px) [default: {TOLERANT.atol_px:g}; "
                   f"--strict {STRICT.atol_px:g}].")
@click.option("--rtol-cov", type=FiniteFloatRange(min=0), default=None,
              help="A cell differs where its covariances differ by more, relative to the matrices (Frobenius norm), "
                   f"or its dof relative to the larger [default: {TOLERANT.rtol_cov:g}; --strict {STRICT.rtol_cov:g}].")
@click.option("--max-share", type=FiniteFloatRange(min=0, max=100), default=None, metavar="PERCENT",
              help=f"Percent of the compared cells allowed to differ [default: {TOLERANT.max_share * 100:g}; "
                   "--strict 0].")
@click.option("--max-px", type=FiniteFloatRange(min=0), default=None,
              help=f"No position of a row that both results report visible may differ by more (px) "
                   f"[default: {TOLERANT.max_px:g}].")
@click.option("--ignore-visible-flips", "visible_flips", type=click.IntRange(min=0), default=None, metavar="N",
              help="Visibility flips allowed beyond near-ties (--strict: beyond none) [default: 0].")
@click.option("--strict", is_flag=True,
              help="The same numbers: every cell within the CSV's rounding, no flip (same machine, same build).")
@click.option("--top", type=click.IntRange(min=0), default=10, show_default=True, help="Differences listed.")
@click.option("--json", "as_json", is_flag=True, help='Print one JSON object instead of the plain report (strict JSON: an infinite '
              'or undefined value, such as an stk covariance, is the string "inf", "-inf" or "nan").')
@click.pass_context
def _compare(ctx: click.Context, path_a: str, path_b: str, atol_px: float | None, rtol_cov: float | None,
             max_share: float | None, max_px: float | None, visible_flips: int | None, strict: bool,
             top: int, as_json: bool) -> None:
    """Compare two track files A and B (.csv, .h5 or .hdf5, any combination).

    \b
    The default passes the same run on another CPU, thread count or
    floating-point order, and fails a real change (README, "Golden files in
    CI"). Points are matched by point_id, frames by index. Exact: the points,
    which frames have a position and (HDF5 against HDF5) the queries and the
    frame count; a point moved on every frame (a moved query) differs. A
    cell (point, frame) differs where its method differs, its positions are
    farther apart than --atol-px, its covariances (relative to the matrices)
    or dof differ by more than --rtol-cov, and (HDF5) likewise its
    measurements z and R. At most --max-share percent of the cells may
    differ, no position by more than --max-px on a row that both files
    report visible (a lost point's prediction may lie far from the other
    run's). A visibility flip where the
    positions differ is a near-tie (a differing cell); a flip on the same
    position counts against --ignore-visible-flips. inf equals only inf of
    the same sign, nan only nan.

    Exit status: 0 agree, 1 differ, 2 unreadable file.
    """
    from condtrack_cli.io.read import read_tracks

    share = None if max_share is None else max_share / 100
    tolerances = with_options(STRICT if strict else TOLERANT, atol_px=atol_px, rtol_cov=rtol_cov, max_share=share,
                              max_px=max_px, visible_flips=visible_flips)
    try:
        a, _ = read_tracks(path_a)
        b, _ = read_tracks(path_b)
    except CondtrackError as error:
        click.echo(f"Error: {error}", err=True)
        ctx.exit(UNREADABLE)
    both_hdf5 = is_hdf5(path_a) and is_hdf5(path_b)
    fields = HDF5_FIELDS if both_hdf5 else CSV_FIELDS
    result = compare_tracks(a, b, tolerances, fields=fields, top=top)
    if as_json:
        click.echo(json.dumps(report_json(result, path_a, path_b), allow_nan=False))
    else:
        click.echo("\n".join(report_lines(result, path_a, path_b)))
    ctx.exit(AGREE if result.agree else DIFFER)


compare_command = click.command("compare")(_compare)
