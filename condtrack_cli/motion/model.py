"""The parametric motion models of paper §5.1: U(x) = P(x) theta, the fit that carries them, A_k of eq. (1).

Conventions (pixel grid, centred and scaled coordinates): :mod:`condtrack_cli.motion.robust`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def warp_maps(model: str, theta: np.ndarray, origin: np.ndarray, length: float,
              shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """x + U(x) on the whole pixel grid of a (H, W) frame: two (H, W) float32 maps (px) for ``cv2.remap``.

    Terms in u only and in v only are summed on a row and a column, then
    broadcast once; only the quadratic model's uv terms cost full-frame passes,
    each a float64 product rounded straight into a float32 buffer and added in place.
    """
    height, width = shape
    u = (np.arange(width) - origin[0]) / length
    v = (np.arange(height) - origin[1]) / length
    maps = []
    term = None  # (H, W) float32 buffer of one uv term
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
                cross.append((theta_j, a, b))
        grid = np.add.outer(along_column.astype(np.float32), along_row.astype(np.float32))
        for theta_j, a, b in cross:
            if term is None:
                term = np.empty((height, width), np.float32)
            np.multiply((v**b)[:, None], (u**a)[None, :], out=term, casting="same_kind")
            term *= np.float32(theta_j)
            grid += term
        maps.append(grid)
    return maps[0], maps[1]
