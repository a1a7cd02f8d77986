"""The scenes (camera_motion, occlusion, ring, illumination, fast, jumps, card, nonrigid): layers and motions, assembled with their truth."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from condtrack_cli.frames.synthetic.affine import _about, _apply, _chain, _invert, _rotation
from condtrack_cli.frames.synthetic.deform import Bumps, random_bumps
from condtrack_cli.frames.synthetic.layers import _background, _Band, _coeffs, _Disk, _grid, _Layer, _Rect, _render
from condtrack_cli.frames.synthetic.truth import BORDER_MARGIN, _geometry, _inside, _pick
from condtrack_cli.types import Queries

DEFAULT_SIZE = (320, 240)  #: (width, height) of the frames unless asked otherwise
SAMPLE_SEEDS = {"camera_motion": 0, "occlusion": 0, "ring": 0}  #: scenes and seeds of the shipped samples


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


# --------------------------------------------------------------------------- assembly

#: Largest frame side (px): rendering a frame takes about 100 bytes a pixel (1.7 GB at 4096 x 4096).
MAX_SIDE = 4096
#: Largest frames x width x height of a scene, whose frames are held in memory (uint8: 1 GiB).
MAX_PIXELS = 2**30


def _start(seed: int, size: tuple[int, int], n_frames: int, noise: float):
    """Check the common arguments (before anything is allocated); return W, H, the scene rng and the noise rng."""
    w, h = (int(v) for v in size)
    if w < 4 * BORDER_MARGIN or h < 4 * BORDER_MARGIN:
        raise ValueError(f"size {w}x{h} is too small (at least {4 * BORDER_MARGIN} px each way)")
    if w > MAX_SIDE or h > MAX_SIDE:
        raise ValueError(f"size {w}x{h} is too large (at most {MAX_SIDE} px each way)")
    if n_frames < 2:
        raise ValueError(f"n_frames must be at least 2, not {n_frames}")
    if w * h * n_frames > MAX_PIXELS:
        raise ValueError(f"{n_frames} frames of {w}x{h} px are too many (at most {MAX_PIXELS} pixels in all)")
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


def jumps(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """Abrupt large motion (the paper's case, issue 31): the camera's velocity is drawn afresh every 3-5 frames.

    Segments alternate slow (2-10 px/frame) and fast (16-28 px/frame, beyond the
    SSD's default 16 px search) translations, each with a rotation of up to 2 deg/frame
    and a zoom of up to 2 %/frame about the frame centre. A segment heads back
    towards the start once the camera is more than 40 px away from it, and zooms
    against the zoom gathered so far, so that the photograph stays sharp. The
    "astronaut" photograph, one layer, ~60 background points queried on frame 0.
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    steps, offset, log_zoom, fast_segment = [], np.zeros(2), 0.0, bool(rng.integers(2))
    while len(steps) < n_frames - 1:
        speed = rng.uniform(16, 28) if fast_segment else rng.uniform(2, 10)
        heading = rng.uniform(0, 2 * np.pi)
        if np.hypot(*offset) > 40:
            heading = np.arctan2(-offset[1], -offset[0]) + rng.uniform(-0.6, 0.6)
        zoom = np.exp(-np.sign(log_zoom or rng.choice([-1.0, 1.0])) * rng.uniform(0.0, np.log(1.02)))
        count = int(rng.integers(3, 6))
        shift = _rotation(heading) @ [speed, 0.0]
        steps += [_about(centre, _rotation(np.radians(rng.uniform(-2, 2)), zoom), shift)] * count
        offset, log_zoom, fast_segment = offset + count * shift, log_zoom + count * np.log(zoom), not fast_segment
    layers = [_background("astronaut", _chain(steps[: n_frames - 1]), (w, h), rng)]
    return _build("jumps", seed, noise, (w, h), layers, ["background"], [(0, 0, 60)], noise_rng)


def card(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """A textured card sweeps in over a slowly panning textured background, stays, and leaves (issue 31).

    Background: the "coffee" photograph panning 0.5-1.5 px/frame with a zoom of
    0.1-0.3 %/frame. Card (layer 1): a rectangle cut from the "camera" photograph,
    35-45 % of the frame wide and 50-65 % high, enters from the left or the right
    edge over 5-7 frames from frame 2 (20-35 px/frame), stays over the middle of
    the frame for 8-11 frames moving with the background, then leaves across the
    frame or back the way it came over 5-7 frames; the last frames are clear, so
    covered points come back. Queries: ~48 background points on frame 0 (many of
    them covered later) and ~12 card points on its first frame in place. A clip
    shorter than the story (up to 30 frames) stops part way, its card points picked
    on its last frame when the card is not in place yet (none while it is outside).
    """
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    pan = _rotation(rng.uniform(0, 2 * np.pi)) @ [rng.uniform(0.5, 1.5), 0.0]
    step = _about(centre, np.eye(2) * rng.uniform(1.001, 1.003), pan)
    background = _background("coffee", _chain([step] * (n_frames - 1)), (w, h), rng)

    half = np.array([rng.uniform(0.175, 0.225) * w, rng.uniform(0.25, 0.325) * h])
    source = np.array([256.0, 256.0])
    shape = _Rect(*(source[0] + [-half[0], half[0]]), *(source[1] + [-half[1], half[1]]))
    side = rng.choice([-1.0, 1.0])  # -1: enters from the left edge
    outside = centre[0] + side * (centre[0] + half[0] + 4)
    stay = centre[0] + rng.uniform(-0.1, 0.1) * w
    arrive = 2 + int(rng.integers(5, 8))
    leave = arrive + int(rng.integers(8, 12))
    gone = max(min(leave + int(rng.integers(5, 8)), n_frames - 3), leave + 1)  # the knots of np.interp increase
    exit_x = outside if rng.integers(2) else 2 * centre[0] - outside
    k = np.arange(n_frames, dtype=float)
    x = np.interp(k, [0, 2, arrive, leave, gone], [outside, outside, stay, stay + (leave - arrive) * pan[0], exit_x])
    y = centre[1] + np.interp(k, [0, arrive, leave], [0, 0, (leave - arrive) * pan[1]])
    to_frame = np.concatenate([np.broadcast_to(np.eye(2), (n_frames, 2, 2)),
                               (np.stack([x, y], axis=1) - source)[..., None]], axis=2)
    occluder = _Layer(_coeffs("camera"), to_frame, shape)
    plan = [(0, 0, 48), (1, min(arrive, n_frames - 1), 12)]
    return _build("card", seed, noise, (w, h), [background, occluder], ["background", "card"], plan, noise_rng)


def nonrigid(seed: int = 0, size: tuple[int, int] = DEFAULT_SIZE, n_frames: int = 30, noise: float = 2.0) -> Scene:
    """A face photograph warped by a smooth deformation that changes over time, with a slow global motion and a slow
    local contrast change (issue 45).

    The face of the "astronaut" photograph (``FACE``, magnified to fill the frame) under a camera drifting
    0.5-1.5 px/frame, turning 0.1-0.3 deg/frame and zooming 0.1-0.2 %/frame about the frame centre (``maps[0]``,
    the global part only), and eight Gaussian displacement bumps 6-10 % of the smaller side wide whose amplitudes
    swing sinusoidally (1.5-3 cycles) up to 8-16 px, scaled down where they would fold the frame
    (:func:`deform.random_bumps`; a frame-k pixel y shows the frame-0 material at ``x0 = u + D(u, k)``,
    u = maps[0, k]^-1 y). The material's contrast about grey 128 is multiplied by ``1 + t_k g(x0)``, g a sum of
    three Gaussian bumps of +-0.25-0.45 (t_k = k / (F - 1)): a patch taken on frame 0 drifts slowly in
    appearance. Truth: the forward map by Newton's method (exact to 1e-10 px).
    One layer, ~60 points queried on frame 0.
    """
    w, h, layer, bumps, contrast, noise_rng = _nonrigid_parts(seed, size, n_frames, noise)
    grid = _grid((w, h))
    frames = np.empty((n_frames, h, w), np.uint8)
    for k in range(n_frames):
        intensity = _nonrigid_intensity(layer, bumps, contrast, grid, k).reshape(h, w)
        frames[k] = np.clip(np.rint(intensity + noise_rng.normal(0.0, noise, (h, w))), 0, 255)
    layer_index, query_frame, x0 = _pick(frames, [layer], [(0, 0, 60)], (w, h))
    camera = layer.maps
    tracks = np.stack([_apply(camera[k], bumps.forward(x0, k)) for k in range(n_frames)], axis=1)
    points = np.arange(len(x0))
    return Scene(name="nonrigid", seed=seed, noise=float(noise), frames=frames,
                 queries=Queries(points, query_frame, tracks[points, query_frame]), tracks=tracks,
                 visible=_inside(tracks, (w, h), 0), layer=layer_index, layer_names=("background",), maps=camera[None])


#: The face (hair to collar) in the "astronaut" photograph: left, top, right, bottom (source pixels).
FACE = (110.0, 8.0, 350.0, 250.0)


def _nonrigid_parts(seed: int, size: tuple[int, int], n_frames: int, noise: float):
    """The ``nonrigid`` scene's W, H, photograph layer (global motion), displacement bumps, contrast-gain bumps
    ((J, 1) directions) and noise rng."""
    w, h, rng, noise_rng = _start(seed, size, n_frames, noise)
    centre = np.array([w - 1, h - 1]) / 2
    drift = _rotation(rng.uniform(0, 2 * np.pi)) @ [rng.uniform(0.5, 1.5), 0.0]
    turn = _rotation(np.radians(rng.choice([-1, 1]) * rng.uniform(0.1, 0.3)),
                     rng.uniform(1.001, 1.002) ** rng.choice([-1, 1]))
    layer = _background("astronaut", _chain([_about(centre, turn, drift)] * (n_frames - 1)), (w, h), rng, FACE)
    bumps = random_bumps(rng, (w, h), n_frames)
    contrast = Bumps(centres=rng.uniform(0.1, 0.9, (3, 2)) * [w - 1, h - 1], directions=np.ones((3, 1)),
                     sigmas=rng.uniform(0.15, 0.25, 3) * min(w, h),
                     amplitudes=rng.choice([-1, 1], 3)[:, None] * rng.uniform(0.25, 0.45, 3)[:, None]
                     * np.arange(n_frames) / (n_frames - 1))
    return w, h, layer, bumps, contrast, noise_rng


def _nonrigid_source(layer: _Layer, bumps: Bumps, y: np.ndarray, k: int) -> np.ndarray:
    """(N, 2) frame-0 positions x0 of the material shown at frame-k positions y (N, 2) px (the backward map)."""
    u = _apply(_invert(layer.maps[k]), y)
    return u + bumps.displacement(u, k)


def _nonrigid_intensity(layer: _Layer, bumps: Bumps, contrast: Bumps, y: np.ndarray, k: int) -> np.ndarray:
    """(N,) noiseless float64 intensity of frame k of the ``nonrigid`` scene at frame-k positions y (N, 2) px."""
    x0 = _nonrigid_source(layer, bumps, y, k)
    gain = 1.0 + contrast.displacement(x0, k)[:, 0]
    return 128.0 + gain * (layer.sample(_apply(_invert(layer.to_frame[0]), x0)) - 128.0)


SCENES: dict[str, Callable[..., Scene]] = {
    "camera_motion": camera_motion,
    "occlusion": occlusion,
    "ring": ring,
    "illumination": illumination,
    "fast": fast,
    "jumps": jumps,
    "card": card,
    "nonrigid": nonrigid,
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


