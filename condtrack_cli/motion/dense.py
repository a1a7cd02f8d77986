"""Motion from one dense field per frame pair: OpenCV's dense inverse search (DIS) (paper §5.1, revised for speed).

The paper estimates the CNLF's local motion by a robust parametric regression on
a 32 x 32 window around every particle, and the CLF's dynamics by the same
regression on the whole frame (Black & Anandan 1996; Odobez & Bouthemy 1995).
This stage (``motion.name: dis``, the default) computes instead one dense field
u(x) from frame k-1 to frame k with Kroeger et al.'s dense inverse search
(ECCV 2016, ``cv2.DISOpticalFlow``: coarse-to-fine inverse-compositional patch
alignment, patches densified by a weighted average, optional variational
refinement) and reads everything the filters need off it:

- Local motion (eq. 5): U(x) = u(x), bilinear between pixels. DIS's patches
  (``patch_size`` px of level ``finest_scale``, i.e. 2^finest_scale times that
  many full-resolution px) play the part of the paper's 32 x 32 window.
- Q_k(x) of the local motion (the paper leaves Q_k open): local_q_floor I plus the
  covariance of the field over the ``local_window`` square around x,
  Cov_W(u) = mean_W(u u^T) - mean_W(u) mean_W(u)^T. Inside one motion it is the
  spread that the motion's own gradient puts on the window (a few 0.001 px^2);
  across a motion boundary, or where DIS's patches disagree, it grows towards
  the squared difference of the motions: the field is inconsistent there, so the
  motion at x is uncertain. The window is 9 px by default, about one DIS patch
  at full resolution: with the paper's 32 px the spread of a boundary reaches
  points 16 px away from it and the shared sets lose up to 0.03 <delta_avg
  (``bench/results.md``, issue 26). Computing it on DIS's finest level only
  (every 2nd pixel on KITTI, 5-node windows, read bilinearly between nodes: 4x
  fewer pixels) was tried: cnlf seq005 0.853 -> 0.848 <delta_avg, KITTI mean
  0.857 -> 0.856 (issue 26, the versus-LK bench).
- Global motion (eq. 1): theta of the parametric model (``model``) fitted to a
  regular sample of at most ``global_samples`` vectors of u by IRLS, cost
  ``robust_cost`` on the vector residual's norm with the scale 1.4826 MAD
  (at least MIN_FLOW_SCALE px), started from the median vector (a translation:
  robust up to half the frame moving otherwise). The scale, the per-pixel
  weights and theta_cov of ``MotionFit`` are those of the brightness residual
  of that theta on the full-resolution frames, exactly as ``robust.py``
  computes them at the end of its own fit (``fit_of``): the routing and the
  misfit term of Q_k read the same quantities whichever stage made the fit.
  Computing the weights on every 2nd pixel only, each pixel taking its 2 x 2
  block's (or bilinear between them), was tried: KITTI mean clf 0.8414 ->
  0.8411 (0.8412 bilinear) <delta_avg, seq011 0.9245 -> 0.9235 (issue 26).
  Refining theta by ``robust.py``'s brightness IRLS from the field's fit was
  tried: it moved KITTI seq059's clf from 0.852 to 0.830 <delta_avg.
- Mean normalisation (``mean_normalization``). OpenCV's DIS matches patches with
  their means subtracted (invariant to a brightness offset between the frames).
  On issue 31's card scene (a textured card entering and leaving at 33-38 px a
  frame over a slowly panning background) that field underestimates the card's
  step at a quarter of its points (seed 1, frames 18 -> 19: 12 of 46 visible
  points more than 2 px off, most moved by under 10 px), so the CNLF and the
  CLF's local dynamics lose the card's own points; without normalisation (``raw``)
  the field is right there (1 of 46) but off by pixels under a brightness change
  (KITTI seq005: auto 0.850 -> 0.797 <delta_avg). ``select`` computes both and
  keeps the raw field where it differs from the normalised one by more than
  ``SELECT_MIN_DIFFERENCE`` px and its warp matches better: the zero-mean SSD
  over the ``local_window`` square of I_{k-1}(x) - I_k(x + u(x)) (bilinear), so
  that a brightness offset does not count (``warp_mismatch``,
  ``raw_matches_better``). Its job being only to catch large steps, the raw field
  is computed on the frames averaged over 2 x 2 px (one DIS level coarser,
  patches ``SELECT_RAW_STRIDE`` px apart), and the choice is made on that grid,
  the window halved (``DenseFlow._selected_field``): 9-13 ms more a KITTI
  1242 x 375 pair (normalised 18-21 ms), a whole ``track -m auto`` on KITTI
  seq005 10-13 % longer in CPU time (a full-resolution raw field and choice:
  30-45 %). It is an option for clips with fast
  independently moving objects, not the default (``normalised``): issue 26's
  speed comes first, and on issue 31's reporting seeds it passes 35 of 40
  checks, not the 37 of the full-resolution version (docs/departures.md).
- Border (``border_pad``, 0 by default): the raw field computed on both frames
  with that many px of replicated border, then cropped, gives DIS's coarse
  levels room at the frame's edge, where a card entering at 33 px a frame is
  missed by both fields (issue 31; measured in docs/departures.md, not the
  default: it breaks the CLF's aperture check of issue 29).
- DIS's finest level: the finest whose pixel count is at most
  ``finest_pixels`` (0 on 320 x 240 frames, 1 on 640 x 480 and on KITTI's
  1242 x 375), unless ``finest_scale`` fixes it: DIS's cost grows with it.

The field is computed once per frame pair and shared by the global and the
local estimators (:class:`DenseFlow`).

Determinism: DIS runs the same arithmetic whatever the number of OpenCV threads
(its parallel loops split independent rows of patches), so the output does not
depend on ``--threads``; a test checks it.
"""

from __future__ import annotations

import functools
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from condtrack_cli.motion.field import LocalField
from condtrack_cli.motion.interface import MotionStages
from condtrack_cli.motion.model import MotionFit, motion_basis
from condtrack_cli.motion.pyramid import frame_pyramid
from condtrack_cli.motion.robust import (
    MAD_TO_SIGMA,
    THETA_PRIOR_STD,
    RobustMotionSettings,
    fit_of,
    frame_normalisation,
    robust_weights,
)
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Frame

#: Floor of the robust scale of the global fit's vector residuals (px).
MIN_FLOW_SCALE = 0.05

#: Most IRLS passes of the global fit, and the change of theta (px) that ends them sooner.
GLOBAL_PASSES = 10
GLOBAL_TOLERANCE = 1e-3

#: ``select``: least difference (px) between the two fields where the raw one may replace the normalised one.
SELECT_MIN_DIFFERENCE = 2.0

#: ``select``: the raw field's DIS patch stride (px of its finest level, on the half-resolution frames).
SELECT_RAW_STRIDE = 3

#: OpenCV's DIS computes no field on a frame under this many px on both sides ("The input image must have either
#: width or height >= 12").
DIS_LEAST_SIDE = 12


class DisMotionSettings(StageSettings):
    frame_windows = ("local_window", "misfit_window")
    model: Literal["translation", "affine", "quadratic"] = Field(
        "quadratic", description="parametric model of the global motion (quadratic: the 8-parameter plane-perspective model)"
    )
    robust_cost: Literal["tukey", "geman_mcclure", "cauchy"] = Field(
        "tukey", description="robust cost rho of the global fit"
    )
    finest_scale: int | None = Field(
        None, ge=0, le=4,
        description="DIS: finest pyramid level computed (0: full resolution; 1: half, upsampled; null: the finest with at most finest_pixels pixels)",
    )
    finest_pixels: int = Field(
        200000, ge=1000, description="with finest_scale null: most pixels of DIS's finest level (its cost grows with them)"
    )
    patch_size: int = Field(8, ge=4, le=32, description="DIS: side of the aligned patches (px of the finest level)")
    patch_stride: int = Field(4, ge=1, le=16, description="DIS: distance between patches (px of the finest level)")
    gradient_iterations: int = Field(12, ge=1, le=100, description="DIS: gradient-descent iterations per patch")
    refinement_iterations: int = Field(
        2, ge=0, le=20, description="DIS: variational refinement iterations per level (0: none)"
    )
    mean_normalization: Literal["normalised", "raw", "select"] = Field(
        "normalised",
        description="DIS: patches matched with their means subtracted (normalised), as they are (raw), or both fields and, per pixel, the one whose warp matches better (select)",
    )
    border_pad: int = Field(
        0, ge=0, le=256,
        description="DIS: px of replicated border added around both frames before the raw field is computed, then cropped (0: none)",
    )
    global_samples: int = Field(
        4000, ge=100, description="most field vectors in the global fit (a regular sample of the frame)"
    )
    q_floor: float = Field(0.05, gt=0, description="floor added to the state noise Q_k of the dominant motion (px^2)")
    local_q_floor: float = Field(
        0.01, gt=0, description="floor added to the local motion's Q_k, the field's spread over local_window (px^2)"
    )
    q_misfit: float = Field(
        100.0, ge=0, description="variance added to Q_k where the neighbourhood rejects the dominant motion (px^2)"
    )
    misfit_window: int = Field(15, ge=3, description="side of the neighbourhood whose robust weights scale q_misfit (px)")
    local_window: int = Field(
        9, ge=3, description="side of the window over which the field's spread gives Q_k of the local motion (px)"
    )

    def least_longer_side(self) -> int:
        """OpenCV's DIS refuses frames under ``DIS_LEAST_SIDE`` px on both sides; ``select``'s raw field runs on
        half-size frames."""
        return DIS_LEAST_SIDE * (2 if self.mean_normalization == "select" else 1)


class DenseFlow:
    """DIS flow of a frame pair, computed once and shared by the global and local estimators.

    ``between(prev, cur)``: (H, W, 2) float32 u(x) px on frame k-1's pixel grid,
    read-only; the last pair's field is kept (the pipeline asks for the global
    fit, then the local field, of the same pair).
    """

    def __init__(self, settings: DisMotionSettings):
        self.settings = settings
        mode = settings.mean_normalization
        #: DIS with mean-normalised patches, and without (run on frames padded by ``border_pad``; for ``select``
        #: on half-resolution frames: ``_selected_field``); None when unused
        self._normalised = _dis(settings, True) if mode != "raw" else None
        self._raw = _dis(settings, False) if mode != "normalised" else None
        if mode == "select":
            self._raw.setPatchStride(SELECT_RAW_STRIDE)
        self._pair: tuple[Frame, Frame] | None = None
        self._flow: np.ndarray | None = None

    def between(self, prev: Frame, cur: Frame) -> np.ndarray:
        if self._pair is None or self._pair[0] is not prev or self._pair[1] is not cur:
            self.prime(prev, cur, self.compute(prev.image, cur.image))
        return self._flow

    def compute(self, prev: np.ndarray, cur: np.ndarray) -> np.ndarray:
        """(H, W, 2) float32 read-only field u(x) px from the (H, W) uint8 image ``prev`` to ``cur``: what
        :meth:`between` returns, computed afresh (``motion/interface.py``, ``PairFieldSource``: the pipeline may call
        this from a thread of its own, the only one that then uses the DIS instances)."""
        level = finest_scale(prev.shape, self.settings)
        a, b = np.ascontiguousarray(prev), np.ascontiguousarray(cur)
        if self._raw is None:
            self._normalised.setFinestScale(level)
            flow = self._normalised.calc(a, b, None)
        elif self._normalised is None:
            self._raw.setFinestScale(level)
            flow = self._raw_field(a, b, self.settings.border_pad)
        else:
            flow = self._selected_field(a, b, level)
        flow = np.ascontiguousarray(flow)
        flow.flags.writeable = False
        return flow

    def prime(self, prev: Frame, cur: Frame, field: np.ndarray) -> None:
        """:meth:`between` of ``prev`` and ``cur`` is ``field`` (:meth:`compute` of their images)."""
        self._pair, self._flow = (prev, cur), field

    def _selected_field(self, a: np.ndarray, b: np.ndarray, level: int) -> np.ndarray:
        """(H, W, 2) ``select``'s field between (H, W) uint8 frames: the normalised field at DIS level ``level``,
        replaced by the raw one where ``raw_matches_better``.

        The raw field, whose job is only to catch the large steps that the normalised one misses, is computed at
        the same level of the frames averaged over 2 x 2 px (INTER_AREA), i.e. one level coarser, with patches
        ``SELECT_RAW_STRIDE`` px apart. The choice is made on that half-resolution grid too, then the raw field is
        upsampled (bilinear, doubled) where it is taken.
        """
        self._normalised.setFinestScale(level)
        flow = self._normalised.calc(a, b, None)
        height, width = a.shape
        half = (width // 2, height // 2)
        # an odd last row or column is left out: INTER_AREA is a plain 2 x 2 mean (and 30 times faster) at exactly half
        a_half, b_half = (cv2.resize(image[: 2 * half[1], : 2 * half[0]], half, interpolation=cv2.INTER_AREA)
                          for image in (a, b))
        self._raw.setFinestScale(level)
        raw_half = self._raw_field(a_half, b_half, self.settings.border_pad // 2)
        normalised_half = cv2.resize(flow, half, interpolation=cv2.INTER_NEAREST) * np.float32(0.5)
        take_raw = raw_matches_better(a_half.astype(np.float32), b_half.astype(np.float32), normalised_half, raw_half,
                                      max(3, self.settings.local_window // 2 | 1))
        raw = cv2.resize(raw_half * np.float32(2), (width, height), interpolation=cv2.INTER_LINEAR)
        return cv2.copyTo(raw, cv2.resize(take_raw, (width, height), interpolation=cv2.INTER_NEAREST), flow)

    def _raw_field(self, a: np.ndarray, b: np.ndarray, pad: int) -> np.ndarray:
        """(H, W, 2) DIS field without mean normalisation between (H, W) uint8 frames, computed on the frames
        padded by ``pad`` px of replicated border (room for DIS's coarse levels at the edge) and cropped."""
        if not pad:
            return self._raw.calc(a, b, None)
        padded = (cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REPLICATE) for image in (a, b))
        return self._raw.calc(*padded, None)[pad : pad + a.shape[0], pad : pad + a.shape[1]]


def _dis(settings: DisMotionSettings, mean_normalised: bool) -> cv2.DISOpticalFlow:
    """A DIS instance with the stage's patch and iteration settings, matching mean-normalised patches or not."""
    dis = cv2.DISOpticalFlow.create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setPatchSize(settings.patch_size)
    dis.setPatchStride(settings.patch_stride)
    dis.setGradientDescentIterations(settings.gradient_iterations)
    dis.setVariationalRefinementIterations(settings.refinement_iterations)
    dis.setUseMeanNormalization(mean_normalised)
    return dis


def warp_mismatch(prev: np.ndarray, cur: np.ndarray, flow: np.ndarray, window: int) -> np.ndarray:
    """(H, W) float32 zero-mean SSD per pixel, over the ``window`` square, of frame k-1 against frame k warped back by u.

    prev, cur: (H, W) float32 grey levels; flow: (H, W, 2) float32 u(x) px. The difference
    d(x) = I_{k-1}(x) - I_k(x + u(x)) (bilinear, borders replicated) less its window mean:
    mean_W(d^2) - mean_W(d)^2, so that a brightness offset between the frames does not count.
    """
    height, width = prev.shape
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    back = cv2.remap(cur, xs + flow[..., 0], ys + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    d = prev - back
    size = (window, window)
    mean = cv2.boxFilter(d, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    return cv2.boxFilter(d * d, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT) - mean * mean


def raw_matches_better(prev: np.ndarray, cur: np.ndarray, normalised: np.ndarray, raw: np.ndarray,
                       window: int) -> np.ndarray:
    """(H, W) uint8 mask, 255 where ``select`` takes the raw field: it differs from the normalised one by more than
    ``SELECT_MIN_DIFFERENCE`` px of the full-resolution frames and its warp matches better (``warp_mismatch``).

    prev, cur: (H, W) float32 half-resolution frames; normalised, raw: (H, W, 2) float32 fields on them (px of
    that grid); window: side of the mismatch's square (px of that grid).
    """
    matches_better = cv2.compare(warp_mismatch(prev, cur, raw, window), warp_mismatch(prev, cur, normalised, window),
                                 cv2.CMP_LT)
    differs = cv2.compare(cv2.magnitude(*cv2.split(raw - normalised)), SELECT_MIN_DIFFERENCE / 2, cv2.CMP_GT)
    return cv2.bitwise_and(matches_better, differs)


def finest_scale(shape: tuple[int, int], settings: DisMotionSettings) -> int:
    """DIS's finest level for (H, W) frames: ``finest_scale``, or the finest with at most ``finest_pixels`` pixels."""
    if settings.finest_scale is not None:
        return settings.finest_scale
    return int(max(0, np.ceil(np.log(shape[0] * shape[1] / settings.finest_pixels) / np.log(4))))


def sample_grid(shape: tuple[int, int], samples: int, margin: int) -> np.ndarray:
    """(N, 2) int positions (x, y) of a regular grid of at most ``samples`` pixels, ``margin`` px inside the frame."""
    height, width = shape
    margin = min(margin, (min(height, width) - 1) // 2)
    inner = (height - 2 * margin) * (width - 2 * margin)
    stride = max(1, int(np.ceil(np.sqrt(inner / samples))))
    ys = np.arange(margin, height - margin, stride)
    xs = np.arange(margin, width - margin, stride)
    grid = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    return grid[:samples]


@functools.lru_cache(maxsize=4)
def sample_design(shape: tuple[int, int], samples: int, margin: int, model: str) -> tuple[np.ndarray, np.ndarray]:
    """The global fit's sample of a (H, W) frame, the same for every pair: (N, 2) int ``sample_grid`` positions
    and the (2N, p) design P(x_i) stacked as rows x_0, y_0, x_1, y_1, ... (read-only, cached per shape)."""
    xy = sample_grid(shape, samples, margin)
    design = motion_basis(model, xy, *frame_normalisation(shape)).reshape(2 * len(xy), -1)
    for array in (xy, design):
        array.flags.writeable = False
    return xy, design


def fit_field(flow: np.ndarray, model: str, cost: str, samples: int, margin: int) -> np.ndarray:
    """(p,) theta (px) of ``model`` fitted to the field by IRLS (module docstring).

    flow: (H, W, 2) float32 px. Residuals e_i = u(x_i) - P(x_i) theta on the
    sample's vectors; weights from |e_i| and the scale 1.4826 MAD of |e_i|.
    """
    xy, design = sample_design(flow.shape[:2], samples, margin, model)
    target = flow[xy[:, 1], xy[:, 0]].astype(np.float64).reshape(-1)  # u_i as x_0, y_0, x_1, y_1, ...
    p = design.shape[1]
    prior = np.eye(p) / THETA_PRIOR_STD**2
    theta = np.zeros(p)
    theta[[0, p // 2]] = np.median(target.reshape(-1, 2), axis=0)  # the translation terms (model.py's order)
    for _ in range(GLOBAL_PASSES):
        norm = np.linalg.norm((target - design @ theta).reshape(-1, 2), axis=1)
        scale = max(MAD_TO_SIGMA * float(np.median(norm)), MIN_FLOW_SCALE)
        weighted = design * np.repeat(robust_weights(cost, norm, scale), 2)[:, None]
        step = np.linalg.solve(weighted.T @ design + scale**2 * prior, weighted.T @ target) - theta
        theta = theta + step
        if np.abs(design @ step).max() < GLOBAL_TOLERANCE:
            break
    return theta


class DisGlobalMotion:
    """Global-support motion stage (``motion/interface.py``): the parametric model fitted to the DIS field."""

    def __init__(self, settings: DisMotionSettings, flow: DenseFlow):
        self.settings = settings
        self.flow = flow
        self.brightness = RobustMotionSettings(model=settings.model, robust_cost=settings.robust_cost, levels=1)

    def fit(self, prev: Frame, cur: Frame) -> MotionFit:
        """The dominant motion from ``prev`` to ``cur``: theta from the field; scale and weights from the frames."""
        settings = self.settings
        field = self.flow.between(prev, cur)
        margin = settings.patch_size * 2 ** finest_scale(field.shape[:2], settings)  # border patches see past the frame
        theta = fit_field(field, settings.model, settings.robust_cost, settings.global_samples, margin)
        return fit_of(frame_pyramid(prev, 1), frame_pyramid(cur, 1), theta, self.brightness)


#: ``window_spread``'s float32 working arrays: five (H, W) planes, an (H, W, 3) and an (H, W, 2) array.
SpreadScratch = tuple[list[np.ndarray], np.ndarray, np.ndarray]


def window_spread(flow: np.ndarray, window: int, scratch: SpreadScratch | None = None) -> np.ndarray:
    """(H, W, 3) float32 Cov_W(u) as (xx, xy, yy) px^2: the field's covariance over the ``window`` square at each pixel.

    flow: (H, W, 2) float32 px. Box means, borders reflected. Rounding may leave
    the diagonal a little below 0 where the field is constant: ``LocalField.noise``
    clips what it samples. scratch: ``spread_scratch`` of the frame shape, reused
    from pair to pair (fresh full-frame arrays cost more in page faults than the
    arithmetic); None: new ones.
    """
    size = (window, window)
    planes, products, mean = scratch if scratch is not None else spread_scratch(flow.shape[:2])
    moments = cv2.boxFilter(_products(flow, planes, products), cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)
    cv2.boxFilter(flow, cv2.CV_32F, size, dst=mean, borderType=cv2.BORDER_REFLECT)
    return cv2.subtract(moments, _products(mean, planes, products), dst=moments)


def spread_scratch(shape: tuple[int, int]) -> SpreadScratch:
    """``window_spread``'s working arrays for (H, W) frames."""
    height, width = shape
    planes = [np.empty((height, width), np.float32) for _ in range(5)]
    return planes, np.empty((height, width, 3), np.float32), np.empty((height, width, 2), np.float32)


def _products(vectors: np.ndarray, planes: list[np.ndarray], products: np.ndarray) -> np.ndarray:
    """(uu, uv, vv) of (H, W, 2) float32 vectors (u, v), written into the (H, W, 3) ``products`` (returned),
    the five (H, W) ``planes`` holding u, v and the three products on the way."""
    u, v, uu, uv, vv = planes
    cv2.split(vectors, [u, v])
    cv2.multiply(u, u, dst=uu)
    cv2.multiply(u, v, dst=uv)
    cv2.multiply(v, v, dst=vv)
    return cv2.merge([uu, uv, vv], dst=products)


class DisLocalMotion:
    """Local-support motion stage (``motion/interface.py``): the DIS field and its spread over the window (eq. 5)."""

    def __init__(self, settings: DisMotionSettings, flow: DenseFlow):
        self.settings = settings
        self.flow = flow
        self._scratch: SpreadScratch | None = None  # window_spread's, for the last frame shape

    def field(self, prev: Frame, cur: Frame, fit: MotionFit) -> LocalField:
        """U(x) = u(x) and Q_k(x) = local_q_floor I + Cov_W(u)(x) from ``prev`` to ``cur``, a node per pixel (``fit``
        unused)."""
        flow = self.flow.between(prev, cur)
        if self._scratch is None or self._scratch[2].shape[:2] != flow.shape[:2]:
            self._scratch = spread_scratch(flow.shape[:2])
        spread = window_spread(flow, self.settings.local_window, self._scratch)
        spread.flags.writeable = False
        return LocalField(flow, spread, 0.0, 1.0, self.settings.local_q_floor)


def make_dis_motion(settings: DisMotionSettings, **_context) -> MotionStages:
    """Dense inverse search: the field shared by the global fit and the local motion; Q_k (``state_noise.py``)."""
    flow = DenseFlow(settings)
    return MotionStages(
        global_motion=DisGlobalMotion(settings, flow),
        local_motion=DisLocalMotion(settings, flow),
        state_noise=StateNoise.of(settings),
        field_source=flow,
    )
