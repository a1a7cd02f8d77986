"""One tracking job (input -> output file), without any click.

``track_input`` is what ``condtrack track`` does for one input; a batch of them
is ``condtrack_cli.batch``.
"""

from __future__ import annotations

import functools
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from condtrack_cli.api import track_sequence
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError, write_error
from condtrack_cli.io.atomic import output_file, publish, staging_folder, through_links
from condtrack_cli.io.formats import track_format
from condtrack_cli.io.write import csv_text, write_tracks
from condtrack_cli.streams import drop


@dataclass(frozen=True)
class RunSummary:
    """What one job did: points, frames, share of visible rows, seconds per frame; or its error."""

    input: str
    output: str | None
    n_points: int = 0
    n_frames: int = 0
    visible_share: float = 0.0
    seconds_per_frame: float = 0.0
    error: str | None = None

    def line(self, method: str) -> str:
        where = f" -> {self.output}" if self.output else ""
        return (
            f"{self.n_points} points, {self.visible_share:.1%} of tracked rows visible, "
            f"{self.seconds_per_frame:.3f} s/frame ({method}){where}"
        )


def check_output_path(path: Path) -> None:
    """Refuse an output path before any work: unknown extension, a folder, missing or read-only folder."""
    track_format(path, "output")
    _, folder = output_file(path)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise CondtrackError(f"{path}: the output folder '{folder}' is not writable")


def track_input(
    input_path: str, config: Config, queries_path: str | None, output_path: str | None, seed: int,
    progress=None, overlay_path: str | None = None, overlay_style=None, staged_path: str | None = None,
) -> RunSummary:
    """Track one input and write its output (CSV on stdout when ``output_path`` is None).

    ``progress(done, total)`` is called after each frame (``api.track_sequence``); None tracks silently.
    ``overlay_style``: what the overlay draws (``render.OverlayStyle``; None: everything).
    ``staged_path``: where the output file is written instead, for the caller to move to ``output_path`` (a batch's
    staging folder, gone when the batch ends); messages name ``output_path``.
    """
    if output_path is not None:
        check_output_path(Path(staged_path or output_path))
    if overlay_path is not None:
        check_overlay_path(Path(overlay_path))
    started = time.perf_counter()
    result, source = track_sequence(input_path, config, queries_path, seed, progress)
    seconds = time.perf_counter() - started
    tracks, info = result.result, result.info
    _write_outputs(result, source, config, output_path, overlay_path, overlay_style, staged_path)
    rows = tracks.has_state
    return RunSummary(
        input=input_path, output=output_path, n_points=len(tracks.queries), n_frames=info.n_frames,
        visible_share=float(tracks.visible[rows].mean()) if rows.any() else 0.0,
        seconds_per_frame=seconds / max(info.n_frames, 1),
    )


def _write_outputs(result, source, config: Config, output_path: str | None, overlay_path: str | None,
                   overlay_style, staged_path: str | None = None) -> None:
    """The track file (the CSV on stdout when ``output_path`` is None) and the overlay video, published together:
    when the overlay fails (a frame its second pass cannot read, a full disk) or is interrupted, the track file is
    not published either (a file already at ``output_path`` stays as it was) and stdout gets nothing. ``staged_path``:
    as in :func:`track_input`."""
    tracks, info = result.result, result.info
    if overlay_path is None:
        if output_path is None:
            write_stdout(csv_text(tracks))
        else:
            write_tracks(tracks, staged_path or output_path, info, result.attributes, config.output, named=output_path)
        return
    from condtrack_cli.render import OverlayStyle, render_overlay

    draw = functools.partial(render_overlay, tracks, source, overlay_path, info.fps, style=overlay_style or OverlayStyle())
    if output_path is None:
        draw()
        write_stdout(csv_text(tracks))
        return
    target = staged_path or output_path
    with staging_folder(target) as staging:
        staged = staging / through_links(target).name
        write_tracks(tracks, staged, info, result.attributes, config.output, named=output_path)
        draw()
        publish(staged, target)


def write_stdout(text: str) -> None:
    """``text`` on stdout, flushed; a CondtrackError when it cannot be written (a redirect to a full disk)."""
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except OSError as error:
        drop(sys.stdout)  # the unwritten rest is not retried at exit
        raise write_error("stdout", error) from None


def check_overlay_path(path: Path) -> None:
    """Refuse an overlay path that is not a video name or whose folder cannot be written, before any work."""
    from condtrack_cli.render import check_video_path

    check_video_path(path)
