"""``condtrack render TRACKS INPUT -o OUT.mp4`` and ``condtrack info TRACKS``: look at a track file."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any, Iterator

import click
import h5py
import numpy as np

from condtrack_cli.errors import CondtrackError
from condtrack_cli.types import METHODS, SequenceInfo, Tracks

_HDF5_SUFFIXES = (".h5", ".hdf5")
#: Root attributes that ``info`` prints in its own rows; any other attribute is printed after them.
_SHOWN_ATTRIBUTES = ("schema_version", "condtrack_version", "input", "width", "height", "n_frames", "fps",
                     "coordinates", "config")


@contextlib.contextmanager
def _particles(path: Path, tracks: Tracks) -> Iterator[Any]:
    """The open ``/particles/xy`` dataset (P, F, N, 2) of an HDF5 track file, or None when it holds none."""
    if path.suffix.lower() not in _HDF5_SUFFIXES:
        yield None
        return
    with h5py.File(path, "r") as f:
        dataset = f.get("particles/xy")
        if dataset is not None and (
            dataset.ndim != 4 or dataset.shape[:2] != tracks.xy.shape[:2] or dataset.shape[3] != 2
        ):
            raise CondtrackError(
                f"{path}: /particles/xy has shape {dataset.shape}, "
                f"expected (P, F, N, 2) with (P, F) = {tracks.xy.shape[:2]}"
            )
        yield dataset


def _matched(tracks: Tracks, meta: dict[str, Any], tracks_path: Path, info: SequenceInfo) -> Tracks:
    """``tracks`` checked against the input; a CSV's tracks (which end at their last row) padded to its length."""
    ours = f"{info.input} has {info.width}x{info.height} px, {info.n_frames} frames"
    if "width" in meta:
        theirs = (int(meta["width"]), int(meta["height"]), int(meta["n_frames"]))
        if theirs != (info.width, info.height, info.n_frames):
            raise CondtrackError(
                f"{tracks_path} was tracked on {theirs[0]}x{theirs[1]} px, {theirs[2]} frames, but {ours}"
            )
        return tracks
    extra = info.n_frames - tracks.xy.shape[1]
    if extra < 0:
        raise CondtrackError(f"{tracks_path} has rows up to frame {tracks.xy.shape[1] - 1}, but {ours}")

    def pad(array: np.ndarray, fill: Any) -> np.ndarray:
        return np.concatenate([array, np.full((len(array), extra) + array.shape[2:], fill, array.dtype)], axis=1)

    return Tracks(tracks.queries, pad(tracks.xy, np.nan), pad(tracks.cov, np.nan), pad(tracks.visible, False),
                  pad(tracks.method, -1), pad(tracks.z, np.nan), pad(tracks.R, np.nan))


@click.command("render")
@click.argument("tracks_path", metavar="TRACKS", type=click.Path(dir_okay=False))
@click.argument("input_path", metavar="INPUT")
@click.option("-o", "--output", "output_path", required=True, type=click.Path(dir_okay=False),
              help="Overlay video, e.g. OUT.mp4 (a folder OUT/ of PNGs when no video codec opens).")
@click.option("--contact-sheet", "sheet_path", type=click.Path(dir_okay=False),
              help="Also write a PNG tiling evenly spaced frames with the overlay.")
@click.option("--trail", type=click.IntRange(min=1), default=10, show_default=True,
              help="Positions joined by each point's trail (1: no trail).")
@click.option("--sheet-frames", type=click.IntRange(min=1), default=6, show_default=True,
              help="Frames on the contact sheet, evenly spaced, first and last included.")
def render_command(tracks_path: str, input_path: str, output_path: str, sheet_path: str | None,
                   trail: int, sheet_frames: int) -> None:
    """Draw the tracks of TRACKS (.h5 or .csv) on the frames of INPUT, the sequence they were tracked on.

    \b
    Per point, in the colour of its method (legend top-left):
      trail       its last --trail positions, darker with age
      ellipse     its 95% covariance ellipse (none when the covariance is
                  undefined or infinite)
      dot / X     filled dot when visible; hollow X when not visible or
                  when the covariance is infinite
      particles   CNLF particles as single pixels, when the file stores them
    Positions are drawn as they are: x right, y down, origin at the centre of
    the top-left pixel (OpenCV's convention).
    """
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.io.read import read_tracks
    from condtrack_cli.render import render_contact_sheet, render_overlay

    tracks_file, output = Path(tracks_path), Path(output_path)
    sheet = Path(sheet_path) if sheet_path else None
    if sheet is not None and sheet.suffix.lower() != ".png":
        raise CondtrackError(f"{sheet}: the contact sheet is a PNG (use a .png name)")
    if sheet is not None and not sheet.parent.is_dir():  # checked now: the sheet is written after the video
        raise CondtrackError(f"{sheet}: the output folder '{sheet.parent}' does not exist")
    tracks, meta = read_tracks(tracks_file)
    source = open_frames(FrameSettings(), input_path)
    if output.resolve() == Path(input_path).resolve():
        raise CondtrackError(f"{output}: the output would replace the input")
    tracks = _matched(tracks, meta, tracks_file, source.info)
    with _particles(tracks_file, tracks) as particles:
        written = render_overlay(tracks, source, output, source.info.fps, trail=trail, particles=particles)
        if sheet is not None:
            render_contact_sheet(tracks, source, sheet, n=sheet_frames, trail=trail, particles=particles)
    click.echo(f"wrote {written}" + (f" and {sheet}" if sheet is not None else ""), err=True)


def _stored(path: Path) -> tuple[str, str]:
    """('stored' / 'not stored') for the measurements and the particles of a track file."""
    if path.suffix.lower() not in _HDF5_SUFFIXES:
        return "not stored (CSV)", "not stored (CSV)"
    with h5py.File(path, "r") as f:
        measurements = "stored" if "measurements/z" in f else "not stored"
        particles = f.get("particles/xy")
        return measurements, (f"stored, {particles.shape[2]} per point" if particles is not None else "not stored")


@click.command("info")
@click.argument("tracks_path", metavar="TRACKS", type=click.Path(dir_okay=False))
def info_command(tracks_path: str) -> None:
    """Print what the track file TRACKS (.h5 or .csv) holds: versions, input, points, config.

    A CSV holds tracks only; what it does not say is printed as n/a.
    """
    from condtrack_cli.io.read import read_tracks

    path = Path(tracks_path)
    tracks, meta = read_tracks(path)
    measurements, particles = _stored(path)
    n_points, n_frames = tracks.xy.shape[:2]
    per_method = dict.fromkeys(METHODS + ("",), 0)
    for name in tracks.point_methods():
        per_method[name] += 1
    split = ", ".join(f"{name or 'no state'} {count}" for name, count in per_method.items() if count)
    started = tracks.has_state
    visible = (f"{tracks.visible[started].mean():.1%} of {int(started.sum())} rows with a state"
               if started.any() else "no row has a state")
    queries = f"{tracks.queries.frame.min()} .. {tracks.queries.frame.max()}" if n_points else "n/a"
    size = f"{meta['width']} x {meta['height']} px" if "width" in meta else "n/a"
    fps = meta.get("fps")
    fps_text = "n/a" if fps is None else f"{fps:g}" + (" (none: a folder of frames)" if fps == 0 else "")
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
