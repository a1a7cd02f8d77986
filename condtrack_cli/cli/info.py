"""``condtrack info TRACKS``: what a track file holds (versions, input, points, config)."""

from __future__ import annotations

from pathlib import Path

import click

#: Root attributes that ``info`` prints in its own rows; any other attribute is printed after them.
_SHOWN_ATTRIBUTES = ("schema_version", "condtrack_version", "input", "width", "height", "n_frames", "fps",
                     "coordinates", "config")


@click.command("info")
@click.argument("tracks_path", metavar="TRACKS", type=click.Path(dir_okay=False))
def info_command(tracks_path: str) -> None:
    """Print what the track file TRACKS (.h5 or .csv) holds: versions, input, points, config.

    A CSV holds tracks only; what it does not say is printed as n/a.
    """
    from condtrack_cli.io.formats import is_hdf5
    from condtrack_cli.io.read import read_tracks, stored_datasets

    path = Path(tracks_path)
    tracks, meta = read_tracks(path)
    measurements, particles = stored_datasets(path)
    n_points, n_frames = tracks.xy.shape[:2]
    split = tracks.method_split()
    started = tracks.has_state
    visible = (f"{tracks.visible[started].mean():.1%} of {int(started.sum())} rows with a state"
               if started.any() else "no row has a state")
    queries = (f"{tracks.queries.frame.min()} .. {tracks.queries.frame.max()}"
               if n_points and is_hdf5(path) else "n/a")  # a CSV holds no queries: its first rows are not them
    size = f"{meta['width']} x {meta['height']} px" if "width" in meta else "n/a"
    fps = meta.get("fps")
    fps_text = "n/a" if fps is None else f"{fps:g}" + (" (none: a folder of frames or a multi-page TIFF)" if fps == 0 else "")
    rows = [
        ("file", str(path)),
        ("schema version", meta.get("schema_version", "n/a")),
        ("condtrack version", meta.get("condtrack_version", "n/a")),
        ("input", meta.get("input", "n/a")),
        ("frame size", size),
        ("frames", str(meta.get("n_frames", n_frames))),
        ("fps", fps_text),
        ("points", f"{n_points}" + (f" ({split})" if split else "")),
        ("visible", visible),
        ("distribution", _distribution(tracks.dof[started])),
        ("query frames", queries),
        ("measurements", measurements),
        ("particles", particles),
        ("coordinates", meta.get("coordinates", "n/a")),
    ]
    rows += [(key, str(meta[key])) for key in sorted(set(meta) - set(_SHOWN_ATTRIBUTES))]
    for key, value in rows:
        click.echo(f"{key + ':':19s}{value}")
    config = meta.get("config")
    click.echo("config (resolved):" + ("".join(f"\n  {line}" for line in config.splitlines()) if config else " n/a"))


def _distribution(dof) -> str:
    """The rows' predictive distribution (docs/schema.md) from their (N,) dof: Student-t with its range, or Gaussian."""
    import numpy as np

    student = dof[np.isfinite(dof)]
    if not student.size:
        return "Gaussian (dof inf)" if dof.size else "n/a"
    share = "" if student.size == dof.size else f" on {student.size / dof.size:.1%} of rows, Gaussian elsewhere"
    return (f"Student-t per row, dof {_above_two(student.min())} .. {student.max():.3g} "
            f"(median {_above_two(np.median(student))}){share}")


def _above_two(dof: float) -> str:
    """``dof`` (> 2) to 3 significant digits, more where fewer would read as 2 or less (the schema's nu > 2: 2.0022
    is '2.002', not '2')."""
    digits = 3
    while float(f"{dof:.{digits}g}") <= 2 and digits < 17:
        digits += 1
    return f"{dof:.{digits}g}"
