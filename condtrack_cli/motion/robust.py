"""Robust parametric motion between two frames, global support (paper §5.1).

The dominant apparent motion from frame k-1 to frame k is a parametric field
U(x) = P(x) theta (paper §5.1), theta the robust regression

    theta_k = argmin_theta sum_{s in R} rho(grad I_k(s)^T P(s) theta + dI/dt(s))

(Black & Anandan 1996; Odobez & Bouthemy 1995), solved the standard way:
Gaussian pyramid (``cv2.pyrDown``), coarse to fine; at each level and iteration
frame k is warped by the current estimate, the brightness-constancy residual is
linearised around it, the robust weights come from the residuals with the scale
1.4826 MAD, and one weighted least-squares step updates theta (IRLS).

Conventions and choices:

- Positions are pixels of the full-resolution frame: x right, y down, (0, 0) at
  the centre of the top-left pixel (OpenCV). ``pyrDown`` keeps the even pixels,
  so pixel (i, j) of level l sits at full-resolution position 2^l (j, i), and
  theta means the same thing at every level.
- P(x) is written in centred, scaled coordinates (u, v) = (x - origin) / length,
  origin the frame centre and length half the longer side, so |u|, |v| <= 1 and
  every parameter is a displacement in pixels (reached at the frame's edge):
  the normal equations stay well conditioned. ``MotionFit.origin`` and
  ``MotionFit.length`` carry them.
- The linearisation uses the mean of grad I_{k-1}(x) and grad I_k(x + U(x))
  (the paper writes grad I_k; the mean is the efficient second-order step of
  Benhimane & Malis 2004: same solution; in our tests it converged from further
  away and in fewer iterations).
- Start. IRLS only converges from a start near the answer, and a strongly
  textured object covering a fifth of the frame can hold it between its own
  motion and the background's. So the coarsest level (at least MIN_COARSE_SIDE
  px on its shorter side) starts twice: from zero motion, and from the better
  of two block-matching hypotheses (``_blocks.py``: exhaustive search, blocks
  moving up to ``search_radius`` - 1/2 px of that level, sequential RANSAC).
  Both are refined with Tukey's biweight whatever the configured cost (a
  redescending first stage, as in MM-estimation); the one with the smaller
  median absolute residual (least median of squares: most pixels decide) goes
  on to the finer levels.
- Approximations for speed: at a level with more than ``max_samples`` textured
  pixels (gradient norm >= ``min_gradient``) the regression uses every m-th of
  them in raster order, a deterministic, spatially even subsample; a level's
  iterations stop once a step moves no sample by more than ``tolerance`` x 2^l
  px of level l (coarse levels need only land in the next level's basin). The
  final full-resolution weights are computed on every pixel.
- Both frames are smoothed by a Gaussian of std PRESMOOTH_SIGMA px first: it
  removes the detail that bilinear interpolation renders worst, which halves
  the interpolation bias on sharp frames (rendered scenes: mean error per
  frame pair 0.025 -> 0.01 px). The weights are those of the smoothed frames.
- A weak Gaussian prior, std ``THETA_PRIOR_STD`` px per parameter, keeps the
  normal equations invertible on textureless frames and the covariance finite
  (about THETA_PRIOR_STD^2 in unconstrained directions).
- Sub-pixel sampling is ``cv2.remap``, which in OpenCV 5 interpolates float32
  images in floating point (older OpenCV quantised positions to 1/32 px).
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from condtrack_cli.motion._blocks import block_displacements, block_hypotheses
from condtrack_cli.motion.model import MotionFit, motion_basis, warp_maps
from condtrack_cli.motion.pyramid import build_pyramid, frame_pyramid, usable_levels
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Frame, Pyramid


class RobustMotionSettings(StageSettings):
    frame_windows = ("local_window", "misfit_window")
    model: Literal["translation", "affine", "quadratic"] = Field(
        "quadratic", description="parametric motion model (quadratic: the 8-parameter plane-perspective model)"
    )
    robust_cost: Literal["tukey", "geman_mcclure", "cauchy"] = Field("tukey", description="robust cost rho")
    levels: int = Field(
        4, ge=1, le=8, description="most Gaussian pyramid levels (the coarsest keeps >= 64 px on its shorter side)"
    )
    iterations: int = Field(5, ge=1, le=50, description="most warp + IRLS iterations per level")
    tolerance: float = Field(
        0.01, ge=0, description="a level stops once a step moves no sample more than this (px; x 2^l on level l)"
    )
    search_radius: int = Field(
        3, ge=0, le=8, description="block-matching search radius for the start (px of the coarsest level; 0: none)"
    )
    max_samples: int = Field(10000, ge=1000, description="most pixels per level in the regression (even subsample)")
    min_gradient: float = Field(
        1.0, ge=0, description="pixels with a smaller gradient norm stay out of the regression (grey/px)"
    )
    min_scale: float = Field(0.5, gt=0, description="floor of the robust residual scale (grey levels)")
    q_floor: float = Field(0.25, gt=0, description="floor added to the state noise Q_k (px^2)")
    q_misfit: float = Field(
        100.0, ge=0, description="variance added to Q_k where the neighbourhood rejects the dominant motion (px^2)"
    )
    misfit_window: int = Field(15, ge=3, description="side of the neighbourhood whose robust weights scale q_misfit (px)")
    local_window: int = Field(32, ge=8, description="side of the local support window (px)")
    local_search: int = Field(
        64, ge=0, description="the local field's coarsest level block-matches each window this far from the global motion (px; 0: none)"
    )


#: Weak prior std of each parameter (px); see the module docstring.
THETA_PRIOR_STD = 100.0


#: Normal-consistency factor of the MAD: sigma = 1.4826 median |r - median r|.
MAD_TO_SIGMA = 1.4826


#: RANSAC inlier distance of a block displacement (px of the level matched).
INLIER_DISTANCE = 0.5

#: Tuning constants c (residuals are divided by c * scale), each giving 95%
#: asymptotic efficiency under Gaussian noise: Tukey 4.6851 and Cauchy 2.3849
#: are the textbook values; 3.7874 is the same criterion for Geman-McClure.
TUNING = {"tukey": 4.6851, "geman_mcclure": 3.7874, "cauchy": 2.3849}


def robust_weights(cost: str, residual: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights rho'(r)/r, normalised to 1 at r = 0, in [0, 1]; same shape and dtype as ``residual``."""
    t2 = residual / (TUNING[cost] * scale)  # a new array: the steps below work in place on it
    np.square(t2, out=t2)
    if cost == "tukey":
        np.subtract(1, t2, out=t2)
        np.maximum(t2, 0, out=t2)
        return np.square(t2, out=t2)
    np.add(t2, 1, out=t2)
    if cost == "geman_mcclure":
        np.square(t2, out=t2)
    return np.divide(1, t2, out=t2)


def robust_scale(residual: np.ndarray, floor: float) -> float:
    """1.4826 MAD of (N,) residuals (grey levels), at least ``floor``."""
    if residual.size == 0:
        return floor
    mad = np.median(np.abs(residual - np.median(residual)))
    return max(MAD_TO_SIGMA * float(mad), floor)


def _sample(stack: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, C) float32 bilinear samples of a (h, w, C) float32 array at (N, 2) float32 positions (px)."""
    if len(xy) == 0:
        return np.zeros((0, stack.shape[2]), np.float32)
    columns = 1024  # cv2.remap wants maps with fewer than 2^15 rows and columns
    padded = np.zeros((-(-len(xy) // columns) * columns, 2), np.float32)
    padded[: len(xy)] = xy
    samples = cv2.remap(stack, padded.reshape(-1, columns, 2), None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return samples.reshape(-1, stack.shape[2])[: len(xy)]


def _select_samples(prev: np.ndarray, support: np.ndarray | None, settings: RobustMotionSettings) -> np.ndarray:
    """(N,) flat indices of the pixels of one level used in the regression (module docstring)."""
    height, width, _ = prev.shape
    candidate = np.zeros((height, width), bool)
    candidate[1:-1, 1:-1] = True  # the Sobel gradient is one-sided on the border
    if support is not None:
        candidate &= support
    candidate &= np.square(prev[:, :, 1]) + np.square(prev[:, :, 2]) >= settings.min_gradient**2
    index = np.flatnonzero(candidate)
    stride = -(-len(index) // settings.max_samples)
    return index[::stride] if stride > 1 else index


class _LevelProblem:
    """The linearised regression of paper §5.1 on the sampled pixels of one pyramid level."""

    def __init__(self, prev: np.ndarray, cur: np.ndarray, level: int, support: np.ndarray | None,
                 model: str, origin: np.ndarray, length: float, settings: RobustMotionSettings):
        self.cur = cur
        self.factor = 2.0**level
        index = _select_samples(prev, support, settings)
        width = prev.shape[1]
        self.level_xy = np.column_stack((index % width, index // width)).astype(np.float32)
        basis = motion_basis(model, self.factor * self.level_xy, origin, length)  # (N, 2, p)
        self.basis_x = np.ascontiguousarray(basis[:, 0])
        self.basis_y = np.ascontiguousarray(basis[:, 1])
        prev_values = prev.reshape(-1, 3)[index].astype(np.float64)
        self.prev_intensity = prev_values[:, 0]
        self.prev_gradient = prev_values[:, 1:]

    def largest_move(self, step: np.ndarray) -> float:
        """Largest displacement (px of this level) that the parameter ``step`` gives a sample."""
        moves = np.concatenate((self.basis_x @ step, self.basis_y @ step))
        return float(np.abs(moves).max(initial=0.0)) / self.factor

    def median_absolute_residual(self, theta: np.ndarray) -> float:
        """Median |r0| (grey) over the samples that stay inside frame k; inf when none does."""
        residual, _, inside = self.linearise(theta)
        return float(np.median(np.abs(residual[inside]))) if inside.any() else np.inf

    def linearise(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At the N samples: residual r0 (N,) grey, design J (N, p) grey/px, (N,) bool inside frame k.

        r(theta + d) ~ r0 + J d with r0 = I_k(x + U(x)) - I_{k-1}(x), the
        paper's dI/dt; r0 and J mean nothing where not ``inside``.
        """
        height, width, _ = self.cur.shape
        shift = np.column_stack((self.basis_x @ theta, self.basis_y @ theta)) / self.factor
        warped = self.level_xy + shift.astype(np.float32)
        inside = np.all((warped >= 0) & (warped <= [width - 1, height - 1]), axis=1)
        cur_values = _sample(self.cur, warped).astype(np.float64)  # float64 throughout: mixed dtypes are slow
        residual = cur_values[:, 0] - self.prev_intensity
        gradient = (0.5 / self.factor) * (cur_values[:, 1:] + self.prev_gradient)  # grey per full-res px
        design = gradient[:, :1] * self.basis_x + gradient[:, 1:] * self.basis_y
        return residual, design, inside


def _normal_equations(design: np.ndarray, residual: np.ndarray, weights: np.ndarray,
                      scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares with the weak prior: (p, p) J^T W J + (scale / THETA_PRIOR_STD)^2 I, (p,) -J^T W r0."""
    weighted = design * weights[:, None]
    prior = (scale / THETA_PRIOR_STD) ** 2 * np.eye(design.shape[1])
    return weighted.T @ design + prior, -(weighted.T @ residual)


def _block_starts(prev: np.ndarray, cur: np.ndarray, level: int, support: np.ndarray | None, model: str,
                  origin: np.ndarray, length: float, settings: RobustMotionSettings) -> list[np.ndarray]:
    """``block_hypotheses`` from one level's (h, w, 3) stacks: up to two (p,) thetas that need no prior guess."""
    factor = 2**level
    centres, moves = block_displacements(prev[:, :, 0], cur[:, :, 0], settings.search_radius,
                                          settings.min_gradient, support)
    basis = motion_basis(model, factor * centres, origin, length)
    return block_hypotheses(basis, factor * moves, INLIER_DISTANCE * factor)


def _irls(problem: _LevelProblem, theta: np.ndarray, cost: str, settings: RobustMotionSettings) -> np.ndarray:
    """Warp + IRLS iterations of the §5.1 regression on one level, from ``theta``; the refined (p,) theta."""
    for _ in range(settings.iterations):
        residual, design, inside = problem.linearise(theta)
        scale = robust_scale(residual[inside], settings.min_scale)
        weights = robust_weights(cost, residual, scale) * inside
        step = np.linalg.solve(*_normal_equations(design, residual, weights, scale))
        theta = theta + step
        if problem.largest_move(step) < settings.tolerance * problem.factor:
            break
    return theta


def _robust_start(problem: _LevelProblem, hypotheses: list[np.ndarray], settings: RobustMotionSettings) -> np.ndarray:
    """(p,) theta on the coarsest level that explains the majority of its pixels (module docstring).

    Zero motion and the block hypothesis with the smaller median absolute
    residual are each refined with Tukey's cost; the refined estimate with the
    smaller median absolute residual (least median of squares) wins.
    """
    starts = [np.zeros(problem.basis_x.shape[1])]
    if hypotheses:
        starts.append(min(hypotheses, key=problem.median_absolute_residual))
    return min((_irls(problem, start, "tukey", settings) for start in starts), key=problem.median_absolute_residual)


def pixel_weights(prev_gray: np.ndarray, cur_gray: np.ndarray, model: str, theta: np.ndarray,
                  origin: np.ndarray, length: float, cost: str, scale: float) -> np.ndarray:
    """(H, W) float32 robust weight of every pixel of frame k-1 under the motion theta; 0 off frame k."""
    map_x, map_y = warp_maps(model, theta, origin, length, prev_gray.shape)
    warped = cv2.remap(cur_gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    return np.nan_to_num(robust_weights(cost, warped - prev_gray, scale), copy=False, nan=0.0)


def estimate_from_pyramids(prev: Pyramid, cur: Pyramid, settings: RobustMotionSettings,
                           support: np.ndarray | None = None) -> MotionFit:
    """``estimate_motion`` on pyramids of frames k-1 and k (same depth, from ``build_pyramid``)."""
    if prev.base.shape != cur.base.shape:
        raise ValueError(f"frames differ in shape: {prev.base.shape} and {cur.base.shape}")
    height, width = prev.base.shape
    origin, length = frame_normalisation((height, width))
    model, cost = settings.model, settings.robust_cost
    coarsest = len(prev.levels) - 1
    for level in reversed(range(coarsest + 1)):
        level_support = None if support is None else support[:: 2**level, :: 2**level]
        problem = _LevelProblem(prev.levels[level], cur.levels[level], level, level_support, model, origin, length,
                                settings)
        if level == coarsest:
            starts = _block_starts(prev.levels[level], cur.levels[level], level, level_support, model, origin,
                                   length, settings)
            theta = _robust_start(problem, starts, settings)
        else:
            theta = _irls(problem, theta, cost, settings)
    return _finished_fit(problem, prev, cur, theta, settings)


def frame_normalisation(shape: tuple[int, int]) -> tuple[np.ndarray, float]:
    """origin (2,) px and length px of P(x) for (H, W) frames: the centre and half the longer side."""
    height, width = shape
    return np.array([(width - 1) / 2, (height - 1) / 2]), max(width, height) / 2


def fit_of(prev: Pyramid, cur: Pyramid, theta: np.ndarray, settings: RobustMotionSettings) -> MotionFit:
    """The ``MotionFit`` of a given (p,) theta (px), e.g. fitted to a dense field: scale, weights, theta_cov.

    As at the end of ``estimate_from_pyramids``: the robust scale and the weighted
    least-squares covariance from the full-resolution level's sampled residuals,
    the per-pixel weights from every pixel.
    """
    origin, length = frame_normalisation(prev.base.shape)
    problem = _LevelProblem(prev.levels[0], cur.levels[0], 0, None, settings.model, origin, length, settings)
    return _finished_fit(problem, prev, cur, np.asarray(theta, np.float64), settings)


def _finished_fit(problem: _LevelProblem, prev: Pyramid, cur: Pyramid, theta: np.ndarray,
                  settings: RobustMotionSettings) -> MotionFit:
    """The fit of ``theta`` on the full-resolution ``problem``: scale, theta_cov, per-pixel weights."""
    model, cost = settings.model, settings.robust_cost
    origin, length = frame_normalisation(prev.base.shape)
    residual, design, inside = problem.linearise(theta)
    scale = robust_scale(residual[inside], settings.min_scale)
    weights = robust_weights(cost, residual, scale) * inside
    dof = max(float(weights.sum()) - len(theta), 1.0)
    residual_std = max(float(np.sqrt(weights @ np.square(residual) / dof)), settings.min_scale)
    normal, _ = _normal_equations(design, residual, weights, residual_std)
    theta_cov = residual_std**2 * np.linalg.inv(normal)  # = (J^T W J / s^2 + I / THETA_PRIOR_STD^2)^-1
    weight_map = pixel_weights(prev.base, cur.base, model, theta, origin, length, cost, scale)
    for array in (theta, theta_cov, origin, weight_map):
        array.flags.writeable = False
    return MotionFit(model, theta, theta_cov, origin, float(length), weight_map, scale)


def estimate_motion(prev: np.ndarray, cur: np.ndarray, settings: RobustMotionSettings,
                    support: np.ndarray | None = None) -> MotionFit:
    """Dominant motion from ``prev`` (frame k-1) to ``cur`` (frame k), paper §5.1.

    prev, cur: (H, W) float32 grey levels. support: (H, W) bool region R of the
    regression on frame k-1's grid (None: the whole frame); the returned weights
    cover every pixel regardless.
    """
    levels = usable_levels(prev.shape, settings.levels)
    return estimate_from_pyramids(build_pyramid(prev, levels), build_pyramid(cur, levels), settings, support)


class GlobalMotion:
    """Global-support motion stage (``motion/interface.py``): the dominant motion of a frame pair."""

    def __init__(self, settings: RobustMotionSettings):
        self.settings = settings

    def fit(self, prev: Frame, cur: Frame) -> MotionFit:
        """The fit from ``prev`` to ``cur``; the frames' pyramids are built once (``frame_pyramid``)."""
        levels = usable_levels(prev.image.shape, self.settings.levels)
        return estimate_from_pyramids(frame_pyramid(prev, levels), frame_pyramid(cur, levels), self.settings)
