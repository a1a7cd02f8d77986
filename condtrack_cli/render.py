"""Off-screen overlay rendering: tracks drawn on their frames, as a video (or PNG folder) and a contact sheet.

Pixel convention: x to the right, y down, origin at the centre of the top-left
pixel. OpenCV draws with the same convention, so positions are drawn as they
are, in fixed point with ``SHIFT`` fractional bits (sub-pixel drawing).

What is drawn on frame k, for every point with a state on k, in the colour of
the method that produced the row (``PALETTE``, legend in the top-left corner):

- its trail: segments joining its last ``trail`` positions (frames k-trail+1..k),
  darker with age;
- the 95% ellipse of its predictive distribution (the Student-t of its covariance
  and ``dof``, ``predictive.py``; chi-square with 2 degrees of freedom, 5.991, for
  a Gaussian row) where the covariance is finite; none where it is NaN (the method has none) or infinite
  (no information); a diamond instead where the ellipse's semi-major axis is
  over the cap (by default half the frame's diagonal: an ellipse larger than the frame);
- a filled dot when visible, a hollow X when not visible or when the covariance
  is infinite;
- CNLF particles, when given, as single pixels in a light tint of the cnlf colour.

``OverlayStyle`` thins this out: only the points that move most, ellipses on
visible points only or none, a smaller cap.

Geometry (ellipse axes and outlines, trail segments, marks) is computed for all
points at once; only the cv2 drawing calls loop, over colours (and over points
for the filled dots, which cv2 cannot batch).
"""

from __future__ import annotations

import itertools
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np

from condtrack_cli.errors import CondtrackError, counted, warn, write_error
from condtrack_cli.frames.readers import opencv_log
from condtrack_cli.io.atomic import atomic_path, check_writable, publish, staging_folder
from condtrack_cli.predictive import ellipse_m2
from condtrack_cli.registry import method_codes
from condtrack_cli.types import Tracks

#: Level of the ellipses drawn.
ELLIPSE_LEVEL = 0.95
#: Fractional bits of the fixed-point coordinates passed to cv2 (1/16 px).
SHIFT = 4
#: BGR colour per method name; a method not listed (one registered by another package) is drawn in ``OTHER_COLOUR``.
PALETTE = {
    "stk": np.array((0, 220, 255)),   # yellow
    "mdr": np.array((255, 160, 0)),   # azure
    "clf": np.array((80, 220, 0)),    # green
    "cnlf": np.array((60, 60, 255)),  # red
}
OTHER_COLOUR = np.array((255, 0, 255))  # magenta
#: Largest coordinate drawn (px, either axis): cv2 takes int32 coordinates with ``SHIFT`` fractional bits, so a
#: position far off the frame (a file's 1e12) would wrap around; the marks and segments reaching it are not drawn.
FARTHEST_PX = 2.0**20
#: Frame rate of the video when the input has none (a folder of frames).
DEFAULT_FPS = 25.0
#: Codec tried for the video; when it does not open, a folder of PNGs is written instead.
FOURCC = "mp4v"
#: Containers of the video, by file extension (OpenCV picks the container from it).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")

_DOT_RADIUS = 2.5       # px, visible mark
_CROSS_HALF = 3.0       # px, half the side of the not-visible X
_DIAMOND_HALF = 6.0     # px, half the diagonal of the ellipse-over-the-cap mark
_ELLIPSE_VERTICES = 64
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.35
_HIDDEN_COLOUR = (230, 230, 230)
_PROBE_BYTES = 4096  # written to tell a full disk from a missing codec or a writer that failed


@dataclass(frozen=True)
class OverlayStyle:
    """What an overlay draws beyond the points' dots and marks.

    points: draw only the ``points`` points that move most (longest path over
    the clip; all when None). ellipses: "all", "visible" (on visible points
    only) or "none". ellipse_cap: largest semi-major axis drawn (px); a larger
    ellipse is drawn as a diamond around the point. None: half the frame's diagonal.
    """

    points: int | None = None
    ellipses: str = "all"
    ellipse_cap: float | None = None


def most_moving(xy: np.ndarray, count: int | None) -> np.ndarray:
    """(P,) bool: the ``count`` points of ``xy`` (P, F, 2) with the longest paths (all when None; ties: lower index)."""
    chosen = np.ones(len(xy), bool)
    if count is not None and count < len(xy):
        steps = np.linalg.norm(np.diff(xy, axis=1), axis=-1)
        length = np.where(np.isfinite(steps), steps, 0.0).sum(axis=1)
        chosen[:] = False
        chosen[np.argsort(-length, kind="stable")[:count]] = True
    return chosen


def ellipse_axes(cov: np.ndarray, dof: np.ndarray | float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes and orientation of the 95% ellipses of the rows' distributions (finite covariances).

    cov: (K, 2, 2) px^2, finite and symmetric; dof: (K,) Student-t nu (inf: Gaussian). Returns ``axes`` (K, 2) in px,
    (major, minor), and ``angle`` (K,) in radians of the major axis, from +x
    towards +y (clockwise on screen, as cv2 measures it). Negative eigenvalues
    (round-off) are clipped to 0.
    """
    a, b, c = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    mean, radius = (a + c) / 2, np.hypot((a - c) / 2, b)
    eigen = np.clip(np.stack([mean + radius, mean - radius], axis=-1), 0.0, None)
    bound = ellipse_m2(ELLIPSE_LEVEL, np.where(np.isnan(dof), np.inf, dof))
    return np.sqrt(np.asarray(bound)[..., None] * eigen), 0.5 * np.arctan2(2 * b, a - c)


def ellipse_outlines(centre: np.ndarray, cov: np.ndarray, dof: np.ndarray | float = np.inf) -> np.ndarray:
    """(K, V, 2) closed outlines of the 95% ellipses around ``centre`` (K, 2) of ``cov`` (K, 2, 2), ``dof`` (K,)."""
    axes, angle = ellipse_axes(cov, dof)
    t = np.linspace(0.0, 2 * np.pi, _ELLIPSE_VERTICES, endpoint=False)
    u, v = axes[:, :1] * np.cos(t), axes[:, 1:] * np.sin(t)  # (K, V) in the ellipse's own frame
    cos, sin = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return np.stack([centre[:, :1] + u * cos - v * sin, centre[:, 1:] + u * sin + v * cos], axis=-1)


def _drawable(points: np.ndarray) -> np.ndarray:
    """(...) bool: the positions ``points`` (..., 2) are finite and within ``FARTHEST_PX`` on both axes."""
    return (np.abs(points) <= FARTHEST_PX).all(axis=-1)


def _fixed(points: np.ndarray) -> np.ndarray:
    """Pixel coordinates (..., 2) -> int32 fixed point with ``SHIFT`` fractional bits."""
    return np.rint(points * (1 << SHIFT)).astype(np.int32)


def _colour(code: int, factor: float = 1.0) -> tuple[int, int, int]:
    """BGR of method ``code`` (an index into ``registry.method_codes()``) scaled by ``factor`` (darker below 1)."""
    colour = PALETTE.get(method_codes()[code], OTHER_COLOUR)
    return tuple(int(round(channel * factor)) for channel in colour)


def _polylines(image: np.ndarray, lines: np.ndarray, colour: tuple[int, int, int], closed: bool) -> None:
    """Draw (K, V, 2) polylines given in pixels, anti-aliased, sub-pixel, but those with a vertex not ``_drawable``."""
    lines = lines[_drawable(lines).all(axis=-1)]
    if len(lines):
        cv2.polylines(image, _fixed(lines), closed, colour, 1, cv2.LINE_AA, SHIFT)


def _put_text(image: np.ndarray, text: str, x: int, y: int, colour: tuple[int, int, int]) -> None:
    """Text with its baseline-left corner at pixel (x, y), on a darkened box for contrast."""
    (width, height), baseline = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    box = image[max(y - height - 2, 0):y + baseline + 1, max(x - 2, 0):x + width + 2]
    box //= 2
    cv2.putText(image, text, (x, y), _FONT, _FONT_SCALE, colour, 1, cv2.LINE_AA)


class Overlay:
    """Draws tracks on their frames; one instance per (tracks, particles) pair.

    tracks: P points over F frames. trail: number of past positions joined by
    the trail (1 = none). style: :class:`OverlayStyle`. particles: (P, F, N, 2) px, NaN where absent, or None;
    any array-like indexable as ``particles[:, k]`` (an open h5py dataset is read
    one frame at a time).
    """

    def __init__(self, tracks: Tracks, *, trail: int = 10, particles=None, style: OverlayStyle = OverlayStyle()):
        if trail < 1:
            raise ValueError(f"trail must be at least 1, got {trail}")
        if particles is not None and (
            len(particles.shape) != 4 or particles.shape[:2] != tracks.xy.shape[:2] or particles.shape[3] != 2
        ):
            raise ValueError(f"particles must be (P, F, N, 2) = {tracks.xy.shape[:2]} + (N, 2), got {particles.shape}")
        if style.ellipses not in ("all", "visible", "none"):
            raise ValueError(f"ellipses must be all, visible or none, got {style.ellipses!r}")
        self.tracks, self.trail, self.particles, self.style = tracks, trail, particles, style
        self.n_frames = tracks.xy.shape[1]
        self.shown = most_moving(tracks.xy, style.points)  # (P,) the points drawn
        self.methods = [int(m) for m in np.unique(tracks.method[self.shown]) if m >= 0]  # for the legend

    def draw(self, k: int, frame: np.ndarray) -> np.ndarray:
        """Frame ``k`` (H, W) uint8 grey -> (H, W, 3) uint8 BGR with the overlay drawn."""
        image = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        t = self.tracks
        xy, cov, dof, method = t.xy[:, k], t.cov[:, k], t.dof[:, k], t.method[:, k]
        has = _drawable(xy) & self.shown
        unbounded = has & np.isinf(cov).any(axis=(1, 2))
        with_ellipse = has & np.isfinite(cov).all(axis=(1, 2)) & (self.style.ellipses != "none")
        if self.style.ellipses == "visible":
            with_ellipse &= t.visible[:, k]
        cap = self.style.ellipse_cap or np.hypot(*image.shape[:2]) / 2
        oversized = with_ellipse.copy()
        oversized[with_ellipse] = ellipse_axes(cov[with_ellipse], dof[with_ellipse])[0][:, 0] > cap
        with_ellipse &= ~oversized
        hidden = has & (~t.visible[:, k] | unbounded)
        if self.particles is not None:
            self._draw_particles(image, np.asarray(self.particles[:, k], dtype=np.float64)[self.shown])
        self._draw_trails(image, k)
        outlines = ellipse_outlines(xy[with_ellipse], cov[with_ellipse], dof[with_ellipse])
        diamonds = xy[oversized][:, None, :] + _DIAMOND_HALF * np.array([[0, -1], [1, 0], [0, 1], [-1, 0]])
        crosses = xy[hidden][:, None, None, :] + _CROSS_HALF * np.array([[[-1, -1], [1, 1]], [[-1, 1], [1, -1]]])
        dots = _fixed(xy[has & ~hidden])
        radius = int(_DOT_RADIUS * (1 << SHIFT))
        for code in self.methods:
            colour = _colour(code)
            _polylines(image, outlines[method[with_ellipse] == code], colour, closed=True)
            _polylines(image, diamonds[method[oversized] == code], colour, closed=True)
            _polylines(image, crosses[method[hidden] == code].reshape(-1, 2, 2), colour, closed=False)
            for centre in dots[method[has & ~hidden] == code].tolist():
                cv2.circle(image, centre, radius, colour, -1, cv2.LINE_AA, SHIFT)
        self._draw_legend(image, diamonds=bool(oversized.any()))
        return image

    def _draw_trails(self, image: np.ndarray, k: int) -> None:
        """Segments between consecutive positions of frames k-trail+1..k, coloured by the later row's method."""
        first = max(0, k - self.trail + 1)
        window = self.tracks.xy[:, first:k + 1]  # (P, L, 2)
        segments = np.stack([window[:, :-1], window[:, 1:]], axis=2)  # (P, L-1, 2, 2)
        valid = np.isfinite(segments).all(axis=(2, 3))
        method = self.tracks.method[:, first + 1:k + 1]  # (P, L-1)
        for column in range(segments.shape[1]):
            age = k - (first + 1 + column)  # 0 for the segment ending on frame k
            factor = 1.0 - 0.6 * age / self.trail
            for code in self.methods:
                chosen = valid[:, column] & (method[:, column] == code) & self.shown
                _polylines(image, segments[chosen, column], _colour(code, factor), closed=False)

    def _draw_particles(self, image: np.ndarray, particles: np.ndarray) -> None:
        """(P, N, 2) particle positions as single pixels (nearest pixel centre) inside the image."""
        points = particles.reshape(-1, 2)
        points = points[_drawable(points)]
        column, row = np.rint(points).astype(np.int64).T
        inside = (column >= 0) & (column < image.shape[1]) & (row >= 0) & (row < image.shape[0])
        tint = (PALETTE["cnlf"] + 255) // 2
        image[row[inside], column[inside]] = tint

    def _draw_legend(self, image: np.ndarray, diamonds: bool) -> None:
        """Method names in their colours, then the marks' meanings (the diamond's when one is drawn), top-left."""
        (_, height), baseline = cv2.getTextSize("Xg", _FONT, _FONT_SCALE, 1)
        step = height + baseline + 3
        rows = [(method_codes()[code], _colour(code)) for code in self.methods] + [("x = not visible", _HIDDEN_COLOUR)]
        if diamonds:
            rows.append(("<> = ellipse over the cap", _HIDDEN_COLOUR))
        for row, (text, colour) in enumerate(rows):
            _put_text(image, text, 4, 4 + height + row * step, colour)


def _drawn(overlay: Overlay, frames: Iterable[np.ndarray], out_path: Path) -> Iterator[np.ndarray]:
    """The frames with the overlay drawn; CondtrackError when their count is not the tracks' F."""
    count = 0
    for k, frame in enumerate(frames):
        if k == overlay.n_frames:
            raise CondtrackError(f"{out_path}: the input has more frames than the tracks ({overlay.n_frames})")
        yield overlay.draw(k, frame)
        count = k + 1
    if count != overlay.n_frames:
        raise CondtrackError(f"{out_path}: the input has {counted(count, 'frame')}, the tracks {overlay.n_frames}")


def _write_png(path: Path, image: np.ndarray, named: Path) -> None:
    """``image`` as the PNG file ``path``; errors name ``named``, the output the user gave."""
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise CondtrackError(f"{named}: OpenCV could not encode the image as PNG")
    try:
        path.write_bytes(encoded.tobytes())
    except OSError as error:
        raise write_error(named, error) from None


def _check_space(folder: Path, named: Path) -> None:
    """A CondtrackError naming ``named`` when a small file cannot be written in ``folder`` (e.g. the disk is full).

    OpenCV's video writer reports no error: a full disk makes it fail to open, or
    drop frames, without a word.
    """
    try:
        with tempfile.TemporaryFile(dir=folder) as probe:
            probe.write(bytes(_PROBE_BYTES))
            probe.flush()
    except OSError as error:
        raise write_error(named, error) from None


def _check_video(video: Path, count: int, named: Path) -> None:
    """A CondtrackError naming ``named`` when the written ``video`` does not read back with ``count`` frames
    (a frame dropped while the disk was full, when the space left is too small for a frame but not for the probe)."""
    capture = cv2.VideoCapture(str(video))
    stored = max(int(capture.get(cv2.CAP_PROP_FRAME_COUNT)), 0) if capture.isOpened() else 0
    capture.release()
    if stored != count:
        raise CondtrackError(f"{named}: the video writer stored {stored} of {count} frames (is the disk full?)")


def check_video_suffix(path: Path) -> None:
    """Refuse a video name whose extension is not a video container (``VIDEO_SUFFIXES``)."""
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise CondtrackError(
            f"{path}: the overlay is an MPEG-4 video; name it {' or '.join(VIDEO_SUFFIXES)}"
            + (" (a PNG picture is --contact-sheet)" if path.suffix.lower() == ".png" else "")
        )


def check_video_path(path: Path) -> None:
    """Refuse, before any work, a video name whose extension is not a video container, or an unwritable folder."""
    check_video_suffix(path)
    check_writable(path)


def render_overlay(tracks: Tracks, frames: Iterable[np.ndarray], out_path: str | Path, fps: float, *,
                   trail: int = 10, particles=None, style: OverlayStyle = OverlayStyle()) -> Path:
    """Draw ``tracks`` on ``frames`` and write the video ``out_path``; returns the path written.

    tracks: P points over F frames (pixel convention of the module docstring).
    frames: the F frames, (H, W) uint8 grey, streamed (e.g. a frame source of
    ``condtrack_cli.frames.readers``). fps: frame rate of the video;
    ``DEFAULT_FPS`` when not positive. trail, particles, style: as in :class:`Overlay`.

    The video is encoded with fourcc ``FOURCC`` in the container named by the
    extension. When no codec opens, the frames are written as ``00000.png``,
    ``00001.png``, ... in the folder ``out_path`` without its extension (which
    must not exist yet), said once as a :class:`CondtrackWarning`, and
    that folder is returned. Either output is whole or absent: it is built
    beside its final path and renamed at the end. CondtrackError when the number
    of frames is not F.
    """
    out_path = Path(out_path)
    images = _drawn(Overlay(tracks, trail=trail, particles=particles, style=style), frames, out_path)
    first = next(images, None)
    if first is None:
        raise CondtrackError(f"{out_path}: no frame to render")
    height, width = first.shape[:2]
    with staging_folder(out_path) as staging:
        video = staging / out_path.name
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter.fourcc(*FOURCC), fps if fps > 0 else DEFAULT_FPS,
                                 (width, height), True)
        if writer.isOpened():
            count = 0
            try:
                with opencv_log(cv2.utils.logging.LOG_LEVEL_ERROR):  # a full disk gives one per frame; the run says it once
                    for image in itertools.chain([first], images):
                        writer.write(image)
                        count += 1
            finally:
                writer.release()
            _check_space(staging, out_path)  # the writer drops frames on a full disk without raising
            _check_video(video, count, out_path)
            publish(video, out_path)
            return out_path
        _check_space(staging, out_path)  # a full disk, not a missing codec, when nothing can be written there
        folder = out_path.with_suffix("")
        if folder.exists():
            raise CondtrackError(f"{out_path}: no video codec opened and the fallback folder '{folder}' already exists")
        warn(f"{out_path}: no video codec opened (fourcc {FOURCC}); writing PNG frames to {folder}/ instead")
        built = staging / folder.name
        built.mkdir()
        for k, image in enumerate(itertools.chain([first], images)):
            _write_png(built / f"{k:05d}.png", image, out_path)
        publish(built, folder)
        return folder


def sheet_frames(n_frames: int, n: int) -> np.ndarray:
    """(min(n, n_frames),) int64 indices of ``n`` evenly spaced frames, first and last included (n = 1: the first
    alone)."""
    return np.rint(np.linspace(0, n_frames - 1, min(n, n_frames))).astype(np.int64)


def render_contact_sheet(tracks: Tracks, frames: Iterable[np.ndarray], out_png: str | Path, n: int = 6,
                         columns: int = 3, *, trail: int = 10, particles=None,
                         style: OverlayStyle = OverlayStyle()) -> Path:
    """Tile ``n`` evenly spaced frames (:func:`sheet_frames`), overlay drawn, into one PNG; returns its path.

    frames: the tracks' F frames, (H, W) uint8, streamed (read up to the last
    tile's). Tiles are H x W, row-major, ``min(columns, n)`` per row, the frame
    index written in each tile's bottom-left corner; the sheet is
    (rows * H, columns * W) with unused tiles black. Written whole or not at all.
    """
    out_png = Path(out_png)
    if n < 1 or columns < 1:
        raise ValueError(f"n and columns must be at least 1, got {n} and {columns}")
    overlay = Overlay(tracks, trail=trail, particles=particles, style=style)
    picks = sheet_frames(overlay.n_frames, n)
    if not len(picks):
        raise CondtrackError(f"{out_png}: no frame to render")
    tiles = []
    for k, frame in enumerate(frames):
        if k in picks:
            tile = overlay.draw(k, frame)
            _put_text(tile, f"frame {k}", 4, tile.shape[0] - 6, (255, 255, 255))
            tiles.append(tile)
        if len(tiles) == len(picks):
            break
    else:
        raise CondtrackError(f"{out_png}: the input ended before frame {picks[len(tiles)]}")
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    height, width = tiles[0].shape[:2]
    sheet = np.zeros((rows * height, columns * width, 3), np.uint8)
    for index, tile in enumerate(tiles):
        row, column = divmod(index, columns)
        sheet[row * height:(row + 1) * height, column * width:(column + 1) * width] = tile
    with atomic_path(out_png) as temporary:
        _write_png(temporary, sheet, out_png)
    return out_png
