"""Synthetic image sequences with exact ground-truth point tracks.

Every scene is a stack of *layers*, bottom to top: layer 0 is a real photograph
(the background, moved by a known affine "camera" motion), the layers above are
textured objects (an occluder band, a disk) moved by their own known rigid maps.
Because each layer is a fixed image moved by an affine map, the position of any
point of layer ``l`` in frame ``k`` is exactly ``maps[l, k] @ (x0, y0, 1)``, with
``(x0, y0)`` its position in frame 0.

Pixel convention (every position here, as in the rest of the package): x to the
right, y down, in pixels, origin (0, 0) at the *centre* of the top-left pixel, so
pixel (row i, column j) has its centre at (x=j, y=i). This is OpenCV's convention.

Rendering of frame k, for a frame of W x H pixels:

1. every pixel centre is mapped back into the background photograph by the
   inverse of the layer's source -> frame k map and the photograph is sampled
   there by cubic B-spline interpolation (``scipy.ndimage.map_coordinates``,
   exact sub-pixel positions whatever the OpenCV version). The source region is
   chosen, magnified if need be, so that no frame ever sees past the photograph;
2. each object is sampled the same way from its texture and composited on top
   with an anti-aliased mask ``alpha = clip(sdf + 1/2, 0, 1)``, ``sdf`` the signed
   distance in pixels to the object's outline (positive inside);
3. global photometry ``128 + contrast * (I - 128) + bias``, then a Gaussian blur
   (only the ``illumination`` scene changes these), then Gaussian noise of standard
   deviation ``noise`` grey levels from ``np.random.default_rng``, then rounding
   and clipping to uint8.

A point is *visible* in frame k when it lies inside the frame (0 <= x <= W-1,
0 <= y <= H-1) and no layer above its own covers it (the upper layer's ``sdf`` is
<= 0 there). Positions are given on every frame, visible or not.

Query points are Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) on a rendered
frame, restricted to the parts of each layer that are *clean*: at least
``BORDER_MARGIN`` pixels inside the frame and ``EDGE_MARGIN`` pixels away from
any layer outline, so that a query's patch never straddles an occluding edge.
Most are picked on frame 0; some scenes also pick background points that are
not visible on frame 0 (behind the occluder, or outside the frame), whose query
frame is then the first frame on which they are clean.

Files written by :func:`write_scene` (all positions with ``%.4f``, ``\\n`` line ends):

- ``00000.png``, ``00001.png``, ...: the frames, 8-bit grey PNG;
- ``queries.csv``: ``point_id,frame,x,y``, one row per point;
- ``tracks.csv``: ``point_id,frame,x,y,visible``, one row per point per frame,
  ordered by point then frame, ``visible`` 0/1;
- ``labels.csv``: ``point_id,layer``, the layer index of each point;
- ``scene.json``: scene name, seed, size, noise, layer names, the pixel
  convention and the per-layer maps ``maps[l][k]`` (2 x 3, frame 0 -> frame k).

Run ``python -m condtrack_cli.frames.synthetic --write-samples DIR`` to write the
shipped samples, or ``--scene NAME --out DIR`` for one scene.
"""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Callable, Protocol

import cv2
import numpy as np
from scipy import ndimage

from condtrack_cli.types import Queries

DEFAULT_SIZE = (320, 240)  #: (width, height) of the frames unless asked otherwise
BORDER_MARGIN = 16  #: a query lies at least this many pixels inside the frame
EDGE_MARGIN = 8  #: ... and this many pixels away from any layer outline
SOURCE_MARGIN = 3  #: source pixels kept between a frame's footprint and the photo edge
COORDINATES = "pixels; x right, y down; origin (0, 0) at the centre of the top-left pixel (OpenCV)"
SAMPLE_SEEDS = {"camera_motion": 0, "occlusion": 0, "ring": 0}  #: scenes and seeds of the shipped samples

_OWN_FILES = re.compile(r"\d{5}\.png|queries\.csv|tracks\.csv|labels\.csv|scene\.json")


@dataclass(frozen=True)
class Scene:
    """A rendered sequence and its exact ground truth.

    Shapes: F frames of H x W pixels, P points, L layers. Positions follow the
    package convention: x right, y down, origin at the centre of the top-left pixel.

    frames: (F, H, W) uint8 grey images.
    queries: one query per point (``point_id`` (P,) = 0..P-1, ``frame`` (P,),
        ``xy`` (P, 2)); ``xy`` equals ``tracks[p, frame[p]]``.
    tracks: (P, F, 2) float64 true positions on every frame.
    visible: (P, F) bool; False where the point is outside the frame or covered.
    layer: (P,) int64 index of the point's layer into ``layer_names``.
    layer_names: (L,) names, bottom to top; 0 is always "background".
    maps: (L, F, 2, 3) float64 affine map of layer l from frame 0 to frame k
        (``maps[l, 0]`` is the identity).
    """

    name: str
    seed: int
    noise: float
    frames: np.ndarray
    queries: Queries
    tracks: np.ndarray
    visible: np.ndarray
    layer: np.ndarray
    layer_names: tuple[str, ...]
    maps: np.ndarray


# --------------------------------------------------------------------------- affine maps
# An affine map is a (..., 2, 3) array [A | t] acting on x (..., 2) as A x + t.


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """m (..., 2, 3) applied to points x (..., 2) -> (..., 2), broadcasting."""
    return np.einsum("...ij,...j->...i", m[..., :2], x) + m[..., 2]


def _invert(m: np.ndarray) -> np.ndarray:
    """Inverse of affine maps (..., 2, 3)."""
    a_inv = np.linalg.inv(m[..., :2])
    return np.concatenate([a_inv, -np.einsum("...ij,...j->...i", a_inv, m[..., 2])[..., None]], axis=-1)


def _compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Map ``outer o inner`` (first inner, then outer), both (..., 2, 3)."""
    a = outer[..., :2] @ inner[..., :2]
    t = np.einsum("...ij,...j->...i", outer[..., :2], inner[..., 2]) + outer[..., 2]
    return np.concatenate([a, t[..., None]], axis=-1)


def _about(centre: np.ndarray, linear: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(2, 3) map x -> linear (x - centre) + centre + shift."""
    return np.concatenate([linear, (centre - linear @ centre + shift)[:, None]], axis=1)


def _rotation(angle: float, scale: float = 1.0) -> np.ndarray:
    """(2, 2) rotation by ``angle`` radians (clockwise on screen, y being down) times ``scale``."""
    c, s = np.cos(angle), np.sin(angle)
    return scale * np.array([[c, -s], [s, c]])


def _chain(increments: list[np.ndarray]) -> np.ndarray:
    """Frame 0 -> frame k maps (F, 2, 3) from the F-1 frame k-1 -> frame k maps."""
    maps = [np.eye(2, 3)]
    for step in increments:
        maps.append(_compose(step, maps[-1]))
    return np.stack(maps)


# --------------------------------------------------------------------------- layers


class _Shape(Protocol):
    def sdf(self, u: np.ndarray) -> np.ndarray:
        """Signed distance in source pixels (positive inside) at points u (..., 2) -> (...)."""


@dataclass(frozen=True)
class _Disk:
    """Disk of ``radius`` around ``centre`` (2,), in source pixels."""

    centre: np.ndarray
    radius: float

    def sdf(self, u: np.ndarray) -> np.ndarray:
        return self.radius - np.hypot(u[..., 0] - self.centre[0], u[..., 1] - self.centre[1])


@dataclass(frozen=True)
class _Band:
    """Vertical band, unbounded in y, with wavy edges (a tree trunk), in source pixels.

    Inside: left + a sin(w y + phase_l) < x < right + a sin(w y + phase_r), w = 2 pi / wavelength.
    The distance is the horizontal one divided by the edge's slope factor.
    """

    left: float
    right: float
    amplitude: float
    wavelength: float
    phase_left: float
    phase_right: float

    def sdf(self, u: np.ndarray) -> np.ndarray:
        x, y = u[..., 0], u[..., 1]
        w = 2 * np.pi / self.wavelength
        aw = self.amplitude * w
        to_left = (x - self.left - self.amplitude * np.sin(w * y + self.phase_left)) / np.hypot(
            1.0, aw * np.cos(w * y + self.phase_left)
        )
        to_right = (self.right + self.amplitude * np.sin(w * y + self.phase_right) - x) / np.hypot(
            1.0, aw * np.cos(w * y + self.phase_right)
        )
        return np.minimum(to_left, to_right)


@dataclass(frozen=True)
class _Layer:
    """A source image moved into the frames.

    coeffs: (h, w) cubic B-spline coefficients of the source image (mirror boundary).
    to_frame: (F, 2, 3) map from source pixels to frame-k pixels (rigid for objects).
    shape: the layer's support in source pixels; None for the background (everywhere).
    """

    coeffs: np.ndarray
    to_frame: np.ndarray
    shape: _Shape | None = None

    @property
    def maps(self) -> np.ndarray:
        """(F, 2, 3) frame 0 -> frame k maps of the layer's points."""
        return _compose(self.to_frame, _invert(self.to_frame[0]))

    def sample(self, u: np.ndarray) -> np.ndarray:
        """Source intensities at source positions u (N, 2) -> (N,) float64."""
        return ndimage.map_coordinates(
            self.coeffs, [u[:, 1], u[:, 0]], order=3, prefilter=False, mode="mirror", output=np.float64
        )

    def sdf(self, x: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Signed distance (px, positive inside) of an object layer at frame positions x (N, K, 2) in frames (K,) -> (N, K)."""
        return self.shape.sdf(_apply(_invert(self.to_frame[frames]), x))


@lru_cache(maxsize=None)
def _coeffs(name: str) -> np.ndarray:
    """Spline coefficients (h, w) of the shipped 8-bit grey asset ``name``.png (read-only, cached)."""
    data = (resources.files("condtrack_cli.frames") / "assets" / f"{name}.png").read_bytes()
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    coeffs = ndimage.spline_filter(image.astype(np.float64), order=3, mode="mirror")
    coeffs.flags.writeable = False
    return coeffs


def _background(photo: str, camera: np.ndarray, size: tuple[int, int], rng: np.random.Generator) -> _Layer:
    """Background layer: ``photo`` moved by the camera maps (F, 2, 3) (frame 0 -> frame k).

    The photograph is placed (at a seeded random offset, magnified only if it is too
    small) so that every frame's footprint lies SOURCE_MARGIN pixels inside it.
    """
    coeffs = _coeffs(photo)
    ph, pw = coeffs.shape
    w, h = size
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    footprint = _apply(_invert(camera)[:, None], corners[None])  # (F, 4, 2) in frame-0 pixels
    low, high = footprint.min(axis=(0, 1)), footprint.max(axis=(0, 1))
    room = np.array([pw, ph], float) - 1 - 2 * SOURCE_MARGIN
    scale = max(1.0, *((high - low) / room))
    slack = np.maximum(room - (high - low) / scale, 0.0)  # 0 along the side that set the scale
    offset = SOURCE_MARGIN - low / scale + rng.uniform(0.0, 1.0, 2) * slack  # source = frame0 / scale + offset
    to_frame0 = np.array([[scale, 0.0, -scale * offset[0]], [0.0, scale, -scale * offset[1]]])
    return _Layer(coeffs, _compose(camera, to_frame0))


# --------------------------------------------------------------------------- ground truth and queries


def _geometry(layers: list[_Layer], layer: np.ndarray, x0: np.ndarray, frames: np.ndarray):
    """Where points are and what covers them.

    layer: (N,) layer index; x0: (N, 2) frame-0 positions; frames: (K,) frame indices.
    Returns positions (N, K, 2), own-layer signed distance (N, K) and the largest
    signed distance of the layers above (N, K; -inf when none is above).
    """
    maps = np.stack([lay.maps[frames] for lay in layers])  # (L, K, 2, 3)
    pos = _apply(maps[layer], x0[:, None])
    own = np.full(pos.shape[:2], np.inf)
    cover = np.full(pos.shape[:2], -np.inf)
    for index, lay in enumerate(layers[1:], start=1):
        sdf = lay.sdf(pos, frames)
        own = np.where(layer[:, None] == index, sdf, own)
        cover = np.where(layer[:, None] < index, np.maximum(cover, sdf), cover)
    return pos, own, cover


def _grid(size: tuple[int, int]) -> np.ndarray:
    """(H * W, 2) pixel-centre positions (x, y) in row-major order."""
    w, h = size
    return np.stack(np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float)), axis=-1).reshape(-1, 2)


def _inside(pos: np.ndarray, size: tuple[int, int], margin: float) -> np.ndarray:
    """(N, K) bool: positions (N, K, 2) at least ``margin`` px inside the W x H frame."""
    w, h = size
    x, y = pos[..., 0], pos[..., 1]
    return (x >= margin) & (y >= margin) & (x <= w - 1 - margin) & (y <= h - 1 - margin)


def _clean(pos: np.ndarray, own: np.ndarray, cover: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N, K) bool: a good place for a query (see the module docstring)."""
    return _inside(pos, size, BORDER_MARGIN) & (own >= EDGE_MARGIN) & (cover <= -EDGE_MARGIN)


def _pick(frames: np.ndarray, layers: list[_Layer], plan, size: tuple[int, int]):
    """Query points from the plan's (layer, frame, count) entries.

    Entries with frame 0 pick clean corners of frame 0; an entry with frame q > 0
    picks clean corners of frame q among the points not visible on frame 0 and
    queries each on its first clean frame. Returns layer (P,), query frame (P,)
    and frame-0 positions (P, 2).
    """
    w, h = size
    grid = _grid(size)
    layer_out, frame_out, x0_out = [], [], []
    for index, q, count in plan:
        x0 = _apply(_invert(layers[index].maps[q]), grid)
        layer = np.full(len(grid), index)
        allowed = _clean(*_geometry(layers, layer, x0, np.array([q])), size)[:, 0]
        if q > 0:
            pos, _, cover = _geometry(layers, layer, x0, np.array([0]))
            allowed &= ~(_inside(pos, size, 0) & (cover <= 0))[:, 0]
        mask = allowed.reshape(h, w).astype(np.uint8)
        corners = cv2.goodFeaturesToTrack(frames[q], count, 0.01, 8, mask=mask, blockSize=7)
        xy = np.empty((0, 2)) if corners is None else corners.reshape(-1, 2).astype(np.float64)
        x0 = _apply(_invert(layers[index].maps[q]), xy)
        layer = np.full(len(xy), index)
        clean = _clean(*_geometry(layers, layer, x0, np.arange(q + 1)), size)
        clean[:, q] = True  # picked there (immune to rounding in the round trip through frame 0)
        layer_out.append(layer)
        frame_out.append(np.argmax(clean, axis=1))
        x0_out.append(x0)
    return np.concatenate(layer_out), np.concatenate(frame_out), np.concatenate(x0_out)


# --------------------------------------------------------------------------- rendering and assembly


def _render(layers: list[_Layer], size: tuple[int, int], photometry: np.ndarray, noise: float, rng) -> np.ndarray:
    """Frames (F, H, W) uint8; photometry (F, 3) holds contrast, bias and blur sigma per frame."""
    w, h = size
    grid = _grid(size)
    n_frames = len(photometry)
    frames = np.empty((n_frames, h, w), np.uint8)
    bottom = layers[0]
    for k, (contrast, bias, blur) in enumerate(photometry):
        image = bottom.sample(_apply(_invert(bottom.to_frame[k]), grid))
        for lay in layers[1:]:
            u = _apply(_invert(lay.to_frame[k]), grid)
            alpha = np.clip(lay.shape.sdf(u) + 0.5, 0.0, 1.0)
            hit = alpha > 0
            image[hit] += alpha[hit] * (lay.sample(u[hit]) - image[hit])
        image = 128.0 + contrast * (image.reshape(h, w) - 128.0) + bias
        image = cv2.GaussianBlur(image, (0, 0), blur, borderType=cv2.BORDER_REFLECT) if blur > 0 else image
        frames[k] = np.clip(np.rint(image + rng.normal(0.0, noise, (h, w))), 0, 255)
    return frames


def _start(seed: int, size: tuple[int, int], n_frames: int, noise: float):
    """Check the common arguments; return W, H, the scene rng and the noise rng."""
    w, h = (int(v) for v in size)
    if w < 4 * BORDER_MARGIN or h < 4 * BORDER_MARGIN:
        raise ValueError(f"size {w}x{h} is too small (at least {4 * BORDER_MARGIN} px each way)")
    if n_frames < 2:
        raise ValueError(f"n_frames must be at least 2, not {n_frames}")
    if not noise >= 0:
        raise ValueError(f"noise must be >= 0, not {noise}")
    scene_seed, noise_seed = np.random.SeedSequence(seed).spawn(2)
    return w, h, np.random.default_rng(scene_seed), np.random.default_rng(noise_seed)


def _build(name, seed, noise, size, layers, layer_names, plan, noise_rng, photometry=None) -> Scene:
    """Render the layers, pick the queries and compute the ground truth."""
    n_frames = len(layers[0].to_frame)
    if photometry is None:
        photometry = np.tile([1.0, 0.0, 0.0], (n_frames, 1))
    frames = _render(layers, size, photometry, noise, noise_rng)
    layer, query_frame, x0 = _pick(frames, layers, plan, size)
    tracks, _, cover = _geometry(layers, layer, x0, np.arange(n_frames))
    points = np.arange(len(layer))
    queries = Queries(points, query_frame, tracks[points, query_frame])
    return Scene(
        name=name,
        seed=seed,
        noise=float(noise),
        frames=frames,
        queries=queries,
        tracks=tracks,
        visible=_inside(tracks, size, 0) & (cover <= 0),
        layer=layer,
        layer_names=tuple(layer_names),
        maps=np.stack([lay.maps for lay in layers]),
    )


# --------------------------------------------------------------------------- scenes


def camera_motion(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """The "camera" photograph under an affine camera motion whose velocity changes abruptly.

    The motion is a chain of segments of 3-5 frames, each with a constant per-frame
    map: a pan (2-4 px/frame), a reversal of the previous segment's motion, a rotation
    (1.5-3 deg/frame about the frame centre), a zoom in or out (2-4 %/frame), or a
    small general affine map. One layer, ~64 background points queried on frame 0.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    kinds, steps = ["pan"], []
    linear, shift = np.eye(2), np.zeros(2)
    while len(steps) < n_frames - 1:
        kind = kinds.pop(0)
        if not kinds:
            kinds = list(rng.permutation(["reverse", "rotate", "zoom", "affine", "pan"]))
        if kind == "pan":
            linear, shift = np.eye(2), _rotation(rng.uniform(0, 2 * np.pi)) @ [rng.uniform(2, 4), 0.0]
        elif kind == "reverse":
            linear = np.linalg.inv(linear)
            shift = -linear @ shift
        elif kind == "rotate":
            linear, shift = _rotation(np.radians(rng.choice([-1, 1]) * rng.uniform(1.5, 3))), np.zeros(2)
        elif kind == "zoom":
            linear, shift = np.eye(2) * rng.uniform(1.02, 1.04) ** rng.choice([-1, 1]), np.zeros(2)
        else:
            linear, shift = np.eye(2) + rng.uniform(-0.015, 0.015, (2, 2)), rng.uniform(-2, 2, 2)
        steps += [_about(centre, linear, shift)] * int(rng.integers(3, 6))
    camera = _chain(steps[: n_frames - 1])
    layers = [_background("camera", camera, (w, h), rng)]
    return _build("camera_motion", seed, noise, (w, h), layers, ["background"], [(0, 0, 64)], noise_rng)


def occlusion(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """Garden-like: a camera pan with mild zoom and a tree-like textured band crossing in front.

    Background: the "coffee" photograph, translated 1-2 px/frame sideways and
    zoomed by 0.2-0.5 %/frame about the frame centre. Occluder (layer 1): a vertical
    band of "gravel" texture, 13 % of the frame wide with wavy edges, moving the same
    way as the background but faster, so that it sweeps 55 % of the frame width over
    the sequence and hides background points for several frames before they come
    back. Queries: ~44 background and ~12 occluder points on frame 0, plus ~8
    background points hidden on frame 0 (behind the band or outside the frame),
    queried on their first clean frame.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    direction = rng.choice([-1.0, 1.0])
    pan = np.array([direction * rng.uniform(1, 2), rng.uniform(-0.3, 0.3)])
    step = _about(centre, np.eye(2) * rng.uniform(1.002, 1.005), pan)
    background = _background("astronaut", _chain([step] * (n_frames - 1)), (w, h), rng)

    half = 0.065 * w
    band = _Band(256 - half, 256 + half, 0.012 * w, rng.uniform(50, 90), *rng.uniform(0, 2 * np.pi, 2))
    speed = pan[0] + direction * 0.55 * w / (n_frames - 1)
    start = centre + [-direction * 0.3 * w, 0.0]
    shifts = start[None] + np.arange(n_frames)[:, None] * [speed, 0.0]
    to_frame = np.concatenate([np.broadcast_to(np.eye(2), (n_frames, 2, 2)), (shifts - 256.0)[..., None]], axis=2)
    occluder = _Layer(_coeffs("gravel"), to_frame, band)

    plan = [(0, 0, 44), (1, 0, 12), (0, n_frames // 2, 8)]
    return _build("occlusion", seed, noise, (w, h), [background, occluder], ["background", "occluder"], plan, noise_rng)


def ring(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """Caltra-like: a textured disk turning on a circular ring over a cluttered background.

    Background: the "gravel" texture under a slow motion (0.5-1 px/frame
    translation, 0.1-0.25 deg/frame rotation). Object (layer 1): a disk cut from the
    "astronaut" photograph, radius 18 % of the smaller frame side, whose centre runs
    0.45-0.65 of a turn around a circle about the frame centre while the disk spins
    3-6 deg/frame on itself. Queries: ~40 background and ~18 disk points on frame 0,
    plus ~8 background points hidden under the disk on frame 0, queried on their
    first clean frame.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    drift = _rotation(rng.uniform(0, 2 * np.pi)) @ [rng.uniform(0.5, 1.0), 0.0]
    step = _about(centre, _rotation(np.radians(rng.choice([-1, 1]) * rng.uniform(0.1, 0.25))), drift)
    background = _background("gravel", _chain([step] * (n_frames - 1)), (w, h), rng)

    side = min(w, h)
    radius, orbit = 0.18 * side, 0.26 * side  # the disk stays 0.06 * side inside the frame
    source_centre = np.array([rng.uniform(200, 310), rng.uniform(150, 300)])
    k = np.arange(n_frames)
    angle = rng.uniform(0, 2 * np.pi) + rng.choice([-1, 1]) * rng.uniform(0.9, 1.3) * np.pi * k / (n_frames - 1)
    spin = rng.uniform(0, 2 * np.pi) + np.radians(rng.choice([-1, 1]) * rng.uniform(3, 6)) * k
    to_frame = np.stack(
        [_about(source_centre, _rotation(s), centre + orbit * np.array([np.cos(a), np.sin(a)]) - source_centre)
         for a, s in zip(angle, spin)]
    )
    disk = _Layer(_coeffs("astronaut"), to_frame, _Disk(source_centre, radius))

    plan = [(0, 0, 40), (1, 0, 18), (0, n_frames // 2, 8)]
    return _build("ring", seed, noise, (w, h), [background, disk], ["background", "disk"], plan, noise_rng)


def illumination(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 24, noise: float = 3.0) -> Scene:
    """The "astronaut" photograph under a smooth camera motion with changing light, blur and noise.

    Camera: pan 1.5-3 px/frame, rotation 0.2-0.4 deg/frame and zoom 0.3 %/frame.
    Photometry per frame: contrast 1 +- 0.3 and bias +-20 grey levels varying
    sinusoidally, and a defocus burst (Gaussian blur up to sigma 1.2-1.8 px) around a
    frame in the middle third. One layer, ~60 background points queried on frame 0.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    pan = _rotation(rng.uniform(0, 2 * np.pi)) @ [rng.uniform(1.5, 3), 0.0]
    turn = _rotation(np.radians(rng.choice([-1, 1]) * rng.uniform(0.2, 0.4)), 1.003)
    layers = [_background("camera", _chain([_about(centre, turn, pan)] * (n_frames - 1)), (w, h), rng)]

    t = np.arange(n_frames) / (n_frames - 1)
    contrast = 1 + 0.3 * np.sin(2 * np.pi * rng.uniform(0.8, 1.2) * t + rng.uniform(0, 2 * np.pi))
    bias = 20 * np.sin(2 * np.pi * rng.uniform(0.5, 1.0) * t + rng.uniform(0, 2 * np.pi))
    blur = rng.uniform(1.2, 1.8) * np.exp(-(((t - rng.uniform(1 / 3, 2 / 3)) / 0.12) ** 2))
    photometry = np.stack([contrast, bias, blur], axis=1)
    return _build("illumination", seed, noise, (w, h), layers, ["background"], [(0, 0, 60)], noise_rng, photometry)


def fast(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 24, noise: float = 2.0) -> Scene:
    """The "coffee" photograph under a fast camera motion: 10-25 px/frame.

    Each frame pans 11.5-23.5 px in a direction that turns 30-50 deg per frame
    (so the camera path stays bounded) plus a rotation of up to 0.4 deg/frame about the
    frame centre. One layer, ~60 background points queried on frame 0.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    heading = rng.uniform(0, 2 * np.pi) + rng.choice([-1, 1]) * np.radians(rng.uniform(30, 50)) * np.arange(n_frames - 1)
    steps = [
        _about(centre, _rotation(np.radians(rng.uniform(-0.4, 0.4))), _rotation(a) @ [rng.uniform(11.5, 23.5), 0.0])
        for a in heading
    ]
    layers = [_background("coffee", _chain(steps), (w, h), rng)]
    return _build("fast", seed, noise, (w, h), layers, ["background"], [(0, 0, 60)], noise_rng)


SCENES: dict[str, Callable[..., Scene]] = {
    "camera_motion": camera_motion,
    "occlusion": occlusion,
    "ring": ring,
    "illumination": illumination,
    "fast": fast,
}


def make_scene(
    name: str,
    seed: int = 0,
    size: tuple[int, int] = DEFAULT_SIZE,
    n_frames: int | None = None,
    noise: float | None = None,
) -> Scene:
    """Scene ``name`` (a key of SCENES) for ``seed``; ``size`` is (width, height).

    ``n_frames`` and ``noise`` (grey levels, standard deviation) default to the
    scene's own. The result is bit-for-bit the same for the same arguments.
    """
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; valid names: {', '.join(SCENES)}")
    options = {key: value for key, value in (("n_frames", n_frames), ("noise", noise)) if value is not None}
    return SCENES[name](seed=seed, size=size, **options)


# --------------------------------------------------------------------------- writing


def write_scene(scene: Scene, out_dir: str | Path) -> Path:
    """Write ``scene`` into ``out_dir`` (files listed in the module docstring); returns the folder.

    The folder is written whole or not at all: files go to a temporary sibling
    folder that then replaces ``out_dir``. An existing ``out_dir`` holding any file
    this writer does not produce is refused (ValueError) rather than deleted.
    """
    out_dir = Path(out_dir)
    if out_dir.exists():
        foreign = [p.name for p in out_dir.iterdir() if not _OWN_FILES.fullmatch(p.name)]
        if foreign:
            raise ValueError(f"{out_dir}: holds '{foreign[0]}', not a synthetic scene folder; not overwriting")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        for k, frame in enumerate(scene.frames):
            _, png = cv2.imencode(".png", frame, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            (staging / f"{k:05d}.png").write_bytes(png.tobytes())
        q = scene.queries
        _write_csv(staging / "queries.csv", "point_id,frame,x,y", [q.point_id, q.frame, q.xy[:, 0], q.xy[:, 1]],
                   "%d,%d,%.4f,%.4f")
        n_points, n_frames = scene.visible.shape
        _write_csv(
            staging / "tracks.csv",
            "point_id,frame,x,y,visible",
            [np.repeat(q.point_id, n_frames), np.tile(np.arange(n_frames), n_points),
             scene.tracks[..., 0].ravel(), scene.tracks[..., 1].ravel(), scene.visible.ravel().astype(int)],
            "%d,%d,%.4f,%.4f,%d",
        )
        _write_csv(staging / "labels.csv", "point_id,layer", [q.point_id, scene.layer], "%d,%d")
        meta = {
            "scene": scene.name,
            "seed": scene.seed,
            "width": scene.frames.shape[2],
            "height": scene.frames.shape[1],
            "n_frames": n_frames,
            "noise": scene.noise,
            "coordinates": COORDINATES,
            "layers": list(scene.layer_names),
            "maps": scene.maps.tolist(),
        }
        text = "{\n" + ",\n".join(f" {json.dumps(key)}: {json.dumps(value)}" for key, value in meta.items()) + "\n}\n"
        (staging / "scene.json").write_text(text, encoding="ascii", newline="\n")
        if out_dir.exists():
            shutil.rmtree(out_dir)
        staging.replace(out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out_dir


def _write_csv(path: Path, header: str, columns: list[np.ndarray], fmt: str) -> None:
    """One row per element of the (N,) columns, formatted by ``fmt``."""
    table = np.empty((len(columns[0]), len(columns)), dtype=object)
    for j, column in enumerate(columns):
        table[:, j] = column
    with open(path, "w", encoding="ascii", newline="\n") as handle:
        np.savetxt(handle, table, fmt=fmt, header=header, comments="", newline="\n")


def write_samples(out_root: str | Path) -> dict[str, Path]:
    """Write the shipped samples (SAMPLE_SEEDS, default sizes) as ``out_root/<scene>``; returns name -> folder."""
    return {name: write_scene(make_scene(name, seed), Path(out_root) / name) for name, seed in SAMPLE_SEEDS.items()}
