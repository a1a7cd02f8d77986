"""``make paper``: the paper's kind of figures on the paper's own scenes, and a forward-backward figure of merit.

The paper (Arnaud, Mémin & Cernuschi-Frías, RFIA 2004, §6) shows Corridor (7 frames, CLF against STK and
MDR), Caltra (CNLF) and Garden (CLF and CNLF through the tree's occlusion) with a few points detected
on frame 0. ``../shared/data`` has the Oxford corridor (``oxford_corridor_nogt``, 11 frames at 512x512)
and the MPEG flower garden (``flowergarden_nogt``, 29 frames at 175x120, a downsampled copy), both
without ground truth. For each sequence and each of STK, CLF and CNLF this module

- tracks Shi-Tomasi points of frame 0 (``POINTS`` at most, ``MIN_DISTANCE`` px apart: the same points
  for every method) forward to the last frame;
- tracks the reversed clip back from the forward track's last positions (queries at frame 0 of the
  reversed clip) and measures the round-trip error, the distance between where the point came back
  on frame 0 and where it started (:func:`round_trip`, :func:`round_trip_stats`);
- draws the forward tracks with their 95 % ellipses as a contact sheet (PNG) and an overlay (mp4), and
  writes ``summary.md`` and ``summary.csv``.

Run: ``python -m condtrack_cli.evaluate.paper_figures --out paper_figures`` (``make paper``). Without
``../shared/data`` it says so and exits 0.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

import condtrack_cli as ct
from condtrack_cli.detect.shi_tomasi import ShiTomasiSettings, detect_points
from condtrack_cli.frames.readers import FrameSettings, open_frames
from condtrack_cli.progress import show_warnings
from condtrack_cli.render import OverlayStyle, render_contact_sheet, render_overlay

REPO = Path(__file__).resolve().parents[2]
#: Where the shared sequences are looked for (as the benchmark does: beside the repository).
SHARED_DATA = REPO.parent / "shared" / "data"
#: The paper's scenes that ship without truth: (folder, the paper's name, frames used: None = all). The paper's
#: Corridor has 7 frames (#0-#6, its Fig. 3), the shipped one 11: the first 7 are used. Garden: all 29 (paper: 27).
SEQUENCES = (("oxford_corridor_nogt", "Corridor", 7), ("flowergarden_nogt", "Garden", None))
METHODS = ("stk", "clf", "cnlf")
#: What ``--methods`` accepts: the default three, and the paper's other baseline (MDR) or condtrack's router.
CHOICES = METHODS + ("mdr", "auto")
#: Most points detected on frame 0 (the paper's figures show about ten; a few dozen give steadier shares).
POINTS = 40
#: Least distance between two detected points (px): spread over the frame as in the paper's figures.
MIN_DISTANCE = 15.0
#: Round-trip error within this many px counts as "came back".
WITHIN = 2.0
#: Frames on a contact sheet.
SHEET_FRAMES = 6
#: Contact sheets and overlays of frames smaller than this (px, the larger side) are drawn enlarged.
MIN_DRAWN_SIDE = 400


@dataclass(frozen=True)
class RoundTrip:
    """One method's forward and backward runs on one sequence.

    start: (P, 2) px, the starting points on frame 0. forward: the forward tracks. back: (P, 2) px where
    each point came back on frame 0 (NaN where it could not be tracked back: no state at the last frame,
    or its last position outside the frame). visible_end: (P,) visible on the last frame going forward;
    visible_back: (P,) visible on frame 0 coming back. left_view: (P,) the forward track's last position is
    outside the frame. seconds: both runs' wall time.
    """

    start: np.ndarray
    forward: ct.Tracks
    back: np.ndarray
    visible_end: np.ndarray
    visible_back: np.ndarray
    left_view: np.ndarray
    seconds: float

    @property
    def error(self) -> np.ndarray:
        """(P,) px round-trip distance, NaN where the point did not come back."""
        return np.linalg.norm(self.back - self.start, axis=-1)


def detect(folder: Path, points: int = POINTS, min_distance: float = MIN_DISTANCE) -> np.ndarray:
    """(M, 2) Shi-Tomasi points of frame 0 of ``folder`` that pass the trackability test (best first)."""
    source = open_frames(FrameSettings(), folder)
    gray = source.read(0).astype(np.float32)
    border = max(8, min(16, min(gray.shape) // 8))
    return detect_points(ShiTomasiSettings(max_points=points, min_distance=min_distance, border=border), gray)


def linked_folder(folder: Path, into: Path, frames: int | None = None, reverse: bool = False) -> Path:
    """A folder ``into`` of symbolic links to the first ``frames`` frames of ``folder`` (all when None), reversed
    when ``reverse`` (frame k of it is then F-1-k)."""
    paths = open_frames(FrameSettings(), folder).paths[:frames]
    into.mkdir(parents=True, exist_ok=True)
    for k, path in enumerate(reversed(paths) if reverse else paths):
        os.symlink(path.resolve(), into / f"{k:05d}{path.suffix.lower()}")
    return into


def reversed_folder(folder: Path, into: Path) -> Path:
    """A folder of symbolic links to ``folder``'s frames in reverse order (frame k of it is F-1-k)."""
    return linked_folder(folder, into, reverse=True)


def round_trip(folder: Path, start: np.ndarray, method: str, work: Path, config=None) -> RoundTrip:
    """Track ``start`` (P, 2) from frame 0 of ``folder`` to its last frame, then back on the reversed clip.

    The backward run's queries are the forward track's last positions (frame 0 of the reversed clip);
    points without a state there or outside the frame do not come back (NaN). ``work``: a folder for the
    reversed clip's links. ``config``: as for :func:`condtrack_cli.track`.
    """
    began = time.perf_counter()
    queries = np.column_stack([np.zeros(len(start)), start])
    forward = ct.track(folder, queries=queries, method=method, config=config)
    width, height = forward.info.width, forward.info.height
    last = forward.xy[:, -1]
    finite = np.isfinite(last).all(axis=-1)
    inside = finite & (last[:, 0] >= 0) & (last[:, 0] <= width - 1) & (last[:, 1] >= 0) & (last[:, 1] <= height - 1)
    back = np.full_like(start, np.nan)
    visible_back = np.zeros(len(start), bool)
    if inside.any():
        clip = reversed_folder(folder, Path(tempfile.mkdtemp(prefix="reversed.", dir=work)))
        backward = ct.track(clip, queries=np.column_stack([np.zeros(inside.sum()), last[inside]]), method=method,
                            config=config)
        back[inside] = backward.xy[:, -1]
        visible_back[inside] = backward.visible[:, -1]
    return RoundTrip(start, forward, back, forward.visible[:, -1].copy(), visible_back, finite & ~inside,
                     time.perf_counter() - began)


def round_trip_stats(trip: RoundTrip, within: float = WITHIN) -> dict[str, float]:
    """The figure of merit of one round trip.

    median_px, p90_px: of the round-trip error of the points that came back (NaN when none did).
    Shares of all P starting points: came_back (tracked to the last frame inside the frame and back to
    frame 0), left_view (the forward track ended outside the frame), within (back within ``within`` px), visible_end (visible on the last frame going forward),
    visible_both (visible there and on frame 0 coming back).
    """
    error = trip.error
    back = error[np.isfinite(error)]
    n = max(len(error), 1)
    return {
        "points": len(error),
        "median_px": float(np.median(back)) if len(back) else float("nan"),
        "p90_px": float(np.percentile(back, 90)) if len(back) else float("nan"),
        "came_back": float(len(back) / n),
        "left_view": float(trip.left_view.sum() / n),
        "within": float((back <= within).sum() / n),
        "visible_end": float(trip.visible_end.sum() / n),
        "visible_both": float((trip.visible_end & trip.visible_back).sum() / n),
    }


def _enlarged(tracks, scale: float):
    """``tracks`` (condtrack_cli.types.Tracks) as drawn on frames enlarged ``scale`` times (pixel centres kept)."""
    return replace(tracks, xy=(tracks.xy + 0.5) * scale - 0.5, cov=tracks.cov * scale**2)


def draw(trip: RoundTrip, folder: Path, sheet: Path, video: Path) -> None:
    """The forward tracks of ``trip`` on ``folder``'s frames: contact sheet ``sheet`` (PNG), overlay ``video`` (mp4)."""
    info = trip.forward.info
    scale = max(1, int(np.ceil(MIN_DRAWN_SIDE / max(info.width, info.height))))
    tracks = _enlarged(trip.forward.result, scale) if scale > 1 else trip.forward.result

    def frames():
        for image in open_frames(FrameSettings(), folder):
            yield cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC) if scale > 1 else image

    style = OverlayStyle(ellipses="visible")  # a lost point's ellipse covers the frame
    render_contact_sheet(tracks, frames(), sheet, n=SHEET_FRAMES, columns=3, trail=info.n_frames, style=style)
    render_overlay(tracks, frames(), video, 4.0, trail=info.n_frames, style=style)


def _fmt(value: float, digits: int = 2) -> str:
    return "n/a" if not np.isfinite(value) else f"{value:.{digits}f}"


def summary(rows: list[dict], seconds: float) -> str:
    lines = [
        "# The paper's sequences: forward-backward round trip",
        "",
        f"`make paper` (`python -m condtrack_cli.evaluate.paper_figures`), {seconds:.0f} s; the corridor's first 7 of its "
        "11 frames (the paper's Corridor has 7), the garden's 29. Shi-Tomasi points of frame 0 "
        f"(at most {POINTS}, {MIN_DISTANCE:g} px apart, the same for every method), tracked to the last frame and back "
        "on the reversed clip from the forward track's last positions. Round-trip error: distance on frame 0 between "
        "where the point came back and where it started; median and p90 over the points that came back (a point "
        "without a state inside the frame on the last frame, e.g. one that left the view, does not). came back, "
        f"within {WITHIN:g} px, visible at the end (forward) and at both ends: shares of all points. "
        "No ground truth: a small round trip is necessary, not sufficient (a point stuck on a static occluder comes back too).",
        "",
        "| sequence | frames | method | points | median (px) | p90 (px) | came back | left the view | within 2 px "
        "| visible at end | visible both ends | wall (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['sequence']} | {row['frames']} | {row['method']} | {row['points']} | {_fmt(row['median_px'])} | "
            f"{_fmt(row['p90_px'])} | {row['came_back']:.2f} | {row['left_view']:.2f} | {row['within']:.2f} | {row['visible_end']:.2f} | {row['visible_both']:.2f} | "
            f"{row['seconds']:.1f} |"
        )
    lines += ["", "Figures: `<sequence>.<method>.sheet.png` (contact sheet: 6 frames, tracks and 95 % ellipses) and "
              "`<sequence>.<method>.mp4` (overlay) beside this file; frames smaller than "
              f"{MIN_DRAWN_SIDE} px are drawn enlarged.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    show_warnings(True)  # library warnings as the command line's ``warning: ...`` lines
    parser = argparse.ArgumentParser(prog="python -m condtrack_cli.evaluate.paper_figures", description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "paper_figures", help="folder written (created)")
    parser.add_argument("--shared-data", type=Path, default=SHARED_DATA, help="folder holding the shared sequences")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=CHOICES,
                        help="methods run (default: stk clf cnlf)")
    args = parser.parse_args(argv)
    folders = [(args.shared_data / name, label, frames) for name, label, frames in SEQUENCES]
    missing = [str(folder) for folder, _, _ in folders if not folder.is_dir()]
    if missing:
        print(f"paper: {', '.join(missing)} absent; nothing to do (the paper's sequences ship in ../shared/data)",
              file=sys.stderr)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    rows = []
    with tempfile.TemporaryDirectory(prefix="paper.") as work:
        for folder, label, frames in folders:
            if frames is not None:
                folder = linked_folder(folder, Path(work) / folder.name, frames)
            start = detect(folder)
            for method in args.methods:
                trip = round_trip(folder, start, method, Path(work))
                stem = f"{folder.name}.{method}"
                draw(trip, folder, args.out / f"{stem}.sheet.png", args.out / f"{stem}.mp4")
                row = {"sequence": folder.name, "paper": label, "frames": trip.forward.info.n_frames,
                       "method": method, **round_trip_stats(trip), "seconds": trip.seconds}
                rows.append(row)
                print(f"paper: {folder.name} {method}: median {_fmt(row['median_px'])} px, within {WITHIN:g} px "
                      f"{row['within']:.2f}, visible at both ends {row['visible_both']:.2f} ({trip.seconds:.1f} s)",
                      file=sys.stderr)
                np.savetxt(args.out / f"{stem}.roundtrip.csv",
                           np.column_stack([np.arange(len(start)), start, trip.forward.xy[:, -1], trip.back,
                                            trip.error, trip.visible_end, trip.visible_back]),
                           delimiter=",", fmt="%.3f", comments="",
                           header="point,x0,y0,x_end,y_end,x_back,y_back,error_px,visible_end,visible_back")
    with open(args.out / "summary.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (args.out / "summary.md").write_text(summary(rows, time.perf_counter() - began))
    print(f"paper: wrote {args.out}/summary.md, summary.csv, contact sheets and overlays", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
