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

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from condtrack_cli.config import StageSettings
from condtrack_cli.motion._blocks import block_displacements, block_hypotheses
from condtrack_cli.registry import register
from condtrack_cli.types import Frame


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


#: Weak prior std of each parameter (px); see the module docstring.
THETA_PRIOR_STD = 100.0

#: Std (px) of the Gaussian smoothing both frames before estimation; see the module docstring.
PRESMOOTH_SIGMA = 1.0

#: Normal-consistency factor of the MAD: sigma = 1.4826 median |r - median r|.
MAD_TO_SIGMA = 1.4826

#: Smallest side (px) of the coarsest pyramid level: below it the level is too
#: blurred to tell a textured object's motion from the background's.
MIN_COARSE_SIDE = 64

#: RANSAC inlier distance of a block displacement (px of the level matched).
INLIER_DISTANCE = 0.5

#: Tuning constants c (residuals are divided by c * scale), each giving 95%
#: asymptotic efficiency under Gaussian noise: Tukey 4.6851 and Cauchy 2.3849
#: are the textbook values; 3.7874 is the same criterion for Geman-McClure.
TUNING = {"tukey": 4.6851, "geman_mcclure": 3.7874, "cauchy": 2.3849}

#: Each parameter's monomial u^a v^b, as (a, b), in the x and y components of U (None: absent).
#: Quadratic is the 8-parameter pseudo-perspective model of Odobez & Bouthemy:
#: U = a0 + a1 u + a2 v + q1 u^2 + q2 uv,  V = a3 + a4 u + a5 v + q1 uv + q2 v^2.
_TERMS = {
    "translation": (((0, 0), None), (None, (0, 0))),
    "affine": (
        ((0, 0), None), ((1, 0), None), ((0, 1), None),
        (None, (0, 0)), (None, (1, 0)), (None, (0, 1)),
    ),
}
_TERMS["quadratic"] = _TERMS["affine"] + (((2, 0), (1, 1)), ((1, 1), (0, 2)))


@dataclass(frozen=True)
class MotionFit:
    """The dominant motion from frame k-1 to frame k (arrays are read-only).

    A position x of frame k-1 moves to x + U(x) in frame k, U(x) = P(x) theta.
    model: 'translation' (p=2) | 'affine' (p=6) | 'quadratic' (p=8).
    theta: (p,) float64, px. theta_cov: (p, p) float64, px^2, from the final
    weighted least squares (independent residuals assumed; see ``state_noise``).
    origin: (2,) px and length: px, the normalisation of P(x) (module docstring).
    weights: (H, W) float32 in [0, 1], final robust weight of each pixel of frame
    k-1 (0 where x + U(x) leaves frame k). scale: robust scale of the final
    residuals I_k(x + U(x)) - I_{k-1}(x), 1.4826 MAD, grey levels.
    """

    model: str
    theta: np.ndarray
    theta_cov: np.ndarray
    origin: np.ndarray
    length: float
    weights: np.ndarray
    scale: float


def n_parameters(model: str) -> int:
    """p, the number of parameters of ``model``."""
    return len(_TERMS[model])


def motion_basis(model: str, xy: np.ndarray, origin: np.ndarray, length: float) -> np.ndarray:
    """P(x) of paper §5.1: (N, 2, p) float64 at (N, 2) positions xy (px)."""
    u, v = ((np.asarray(xy, np.float64) - origin) / length).T
    basis = np.zeros((len(u), 2, n_parameters(model)))
    for j, monomials in enumerate(_TERMS[model]):
        for component, exponents in enumerate(monomials):
            if exponents is not None:
                basis[:, component, j] = u ** exponents[0] * v ** exponents[1]
    return basis


def displacement(fit: MotionFit, xy: np.ndarray) -> np.ndarray:
    """U(x) = P(x) theta: (N, 2) px at (N, 2) positions xy of frame k-1."""
    return motion_basis(fit.model, xy, fit.origin, fit.length) @ fit.theta


def jacobian(fit: MotionFit, xy: np.ndarray) -> np.ndarray:
    """d(x + U(x))/dx: (N, 2, 2) at (N, 2) positions xy (px).

    This is A_k of eq. (1), the same at every point for translation and affine
    (then b_k = x + U(x) - A_k x, any x); for quadratic it is the linearisation
    of the dynamics at each point.
    """
    u, v = ((np.asarray(xy, np.float64) - fit.origin) / fit.length).T
    jac = np.zeros((len(u), 2, 2))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    for theta_j, monomials in zip(fit.theta, _TERMS[fit.model]):
        for component, exponents in enumerate(monomials):
            if exponents is None:
                continue
            a, b = exponents
            if a:
                jac[:, component, 0] += theta_j * a * u ** (a - 1) * v**b / fit.length
            if b:
                jac[:, component, 1] += theta_j * b * u**a * v ** (b - 1) / fit.length
    return jac


def neighbourhood_support(fit: MotionFit, xy: np.ndarray, window: int) -> np.ndarray:
    """(N,) mean robust weight of the dominant-motion fit over a ``window`` x ``window`` square at each of (N, 2) xy.

    Near 1 where the neighbourhood follows the dominant motion, near 0 where it
    does not (another object, parallax, an occluder). Positions are rounded to
    the nearest pixel and clamped to the frame.
    """
    mean = cv2.boxFilter(fit.weights, -1, (window, window), borderType=cv2.BORDER_REFLECT)
    h, w = mean.shape
    cols = np.clip(np.rint(xy[:, 0]), 0, w - 1).astype(int)
    rows = np.clip(np.rint(xy[:, 1]), 0, h - 1).astype(int)
    return mean[rows, cols].astype(np.float64)


def state_noise(
    fit: MotionFit, xy: np.ndarray, q_floor: float, q_misfit: float = 0.0, misfit_window: int = 15
) -> np.ndarray:
    """Q_k at (N, 2) positions: (N, 2, 2) px^2.

    Q_k = P(x) Sigma_theta P(x)^T + (q_floor + q_misfit (1 - w(x))^2) I, with
    w(x) the mean robust weight around x (``neighbourhood_support``).

    The paper only says Q_k is estimated from the images. Our choice has three
    parts: the uncertainty of the fitted motion propagated to the point; a floor
    for what any parametric model leaves out; and a model-misfit term read off
    the robust fit itself: where the neighbourhood of x was rejected as outliers
    the dominant motion says little about x, so the point may move by up to a
    few pixels more (``python -m condtrack_cli.evaluate.bench --support SEQUENCE``
    on the real sequences of ../shared/data: one-step prediction error median
    about 10 px where the support is below 0.4, 0.45-1.1 px where it is >= 0.8).
    The weighted-least-squares Sigma_theta treats pixels as independent, so it is
    tiny on textured frames; it grows where the fit is poorly constrained.
    """
    basis = motion_basis(fit.model, xy, fit.origin, fit.length)
    isotropic = q_floor + (q_misfit * (1 - neighbourhood_support(fit, xy, misfit_window)) ** 2 if q_misfit else 0.0)
    return basis @ fit.theta_cov @ basis.transpose(0, 2, 1) + np.multiply.outer(isotropic, np.eye(2))


def robust_weights(cost: str, residual: np.ndarray, scale: float) -> np.ndarray:
    """IRLS weights rho'(r)/r, normalised to 1 at r = 0, in [0, 1]; same shape and dtype as ``residual``."""
    t2 = np.square(residual / (TUNING[cost] * scale))
    if cost == "tukey":
        return np.square(np.clip(1 - t2, 0, None))
    if cost == "geman_mcclure":
        return 1 / np.square(1 + t2)
    return 1 / (1 + t2)


def robust_scale(residual: np.ndarray, floor: float) -> float:
    """1.4826 MAD of (N,) residuals (grey levels), at least ``floor``."""
    if residual.size == 0:
        return floor
    mad = np.median(np.abs(residual - np.median(residual)))
    return max(MAD_TO_SIGMA * float(mad), floor)


@dataclass(frozen=True)
class Pyramid:
    """A frame's Gaussian pyramid with its gradients.

    base: (H, W) float32, the frame smoothed by a Gaussian of std PRESMOOTH_SIGMA
    px (level 0). levels: finest first, (h_l, w_l, 3) float32 [I, dI/dx, dI/dy]
    in grey levels and grey per pixel of that level (3x3 Sobel / 8).
    """

    base: np.ndarray
    levels: list[np.ndarray]


def build_pyramid(gray: np.ndarray, levels: int) -> Pyramid:
    """Gaussian pyramid (``cv2.pyrDown``) of a (H, W) frame, with gradients, ``levels`` deep."""
    return deepen(Pyramid(cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), PRESMOOTH_SIGMA), []), levels)


def deepen(pyramid: Pyramid, levels: int) -> Pyramid:
    """``pyramid`` with coarser levels appended (``cv2.pyrDown`` of the coarsest image) until ``levels`` deep."""
    stacks = list(pyramid.levels)
    image = stacks[-1][:, :, 0] if stacks else pyramid.base
    for level in range(len(stacks), levels):
        if level:
            image = cv2.pyrDown(image)
        gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        stacks.append(cv2.merge((image, gx, gy)))
    return Pyramid(pyramid.base, stacks)


def usable_levels(shape: tuple[int, int], levels: int) -> int:
    """``levels`` capped so that the coarsest level's shorter side is >= MIN_COARSE_SIDE px."""
    return min(levels, 1 + max(0, int(np.log2(min(shape) / MIN_COARSE_SIDE))))


def frame_pyramid(frame: Frame, levels: int) -> Pyramid:
    """``build_pyramid`` of ``frame.gray``, cached in ``frame.cache['motion.pyramid']``, ``levels`` deep."""
    cached = frame.cache.get("motion.pyramid")
    if cached is None:
        cached = build_pyramid(frame.gray, levels)
    elif len(cached.levels) < levels:  # a deeper one asked for later: the cached levels are kept
        cached = deepen(cached, levels)
    frame.cache["motion.pyramid"] = cached
    return Pyramid(cached.base, cached.levels[:levels])


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


def warp_maps(model: str, theta: np.ndarray, origin: np.ndarray, length: float,
              shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """x + U(x) on the whole pixel grid of a (H, W) frame: two (H, W) float32 maps (px) for ``cv2.remap``.

    Terms in u only and in v only are summed on a row and a column, then
    broadcast once; only the quadratic model's uv terms cost full-frame passes.
    """
    height, width = shape
    u = (np.arange(width) - origin[0]) / length
    v = (np.arange(height) - origin[1]) / length
    maps = []
    for component in (0, 1):
        along_row = np.arange(width, dtype=np.float64) if component == 0 else np.zeros(width)
        along_column = np.arange(height, dtype=np.float64) if component == 1 else np.zeros(height)
        cross = []
        for theta_j, monomials in zip(theta, _TERMS[model]):
            if monomials[component] is None:
                continue
            a, b = monomials[component]
            if b == 0:
                along_row += theta_j * u**a
            elif a == 0:
                along_column += theta_j * v**b
            else:
                cross.append(np.float32(theta_j) * np.outer(v**b, u**a).astype(np.float32))
        maps.append(sum(cross, along_row.astype(np.float32)[None, :] + along_column.astype(np.float32)[:, None]))
    return maps[0], maps[1]


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
    origin = np.array([(width - 1) / 2, (height - 1) / 2])
    length = max(width, height) / 2
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
    """Global-support motion stage: one fit per frame pair, shared through ``Frame.cache``."""

    def __init__(self, settings: RobustMotionSettings):
        self.settings = settings

    def fit(self, prev: Frame, cur: Frame) -> MotionFit:
        """The fit from ``prev`` to ``cur``, cached in ``cur.cache['motion.global']``.

        The cached fit is reused when asked for with the same previous frame and
        settings (``cur.cache['motion.global.key']``); pyramids are cached per frame.
        """
        key = (prev.index, self.settings)
        if cur.cache.get("motion.global.key") == key:
            return cur.cache["motion.global"]
        levels = usable_levels(prev.image.shape, self.settings.levels)
        fit = estimate_from_pyramids(frame_pyramid(prev, levels), frame_pyramid(cur, levels), self.settings)
        cur.cache["motion.global"] = fit
        cur.cache["motion.global.key"] = key
        return fit


@register("motion", "robust", RobustMotionSettings, "robust parametric motion, coarse to fine with IRLS")
def make_robust_motion(settings: RobustMotionSettings, **_context) -> GlobalMotion:
    """Robust parametric motion, global support."""
    return GlobalMotion(settings)
