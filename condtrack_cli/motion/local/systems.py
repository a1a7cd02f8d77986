"""Per-node normal equations of the local field's windows and their small symmetric solves (both supports at once)."""

from __future__ import annotations

import numpy as np

from condtrack_cli.motion.local.windows import _MONOMIALS, _Layout, _window_sums

#: Relative floor of each window system's diagonal: float32 sums of rank-one terms
#: are positive semi-definite to about 1e-6 of their largest entry only.
NUMERICAL_RIDGE = 1e-5


# Small symmetric systems, one per support and node: nested lists of (2, hn, wn) arrays.


def _cholesky(matrix: list) -> list:
    """Lower Cholesky factor L (L[i][j], j <= i) of positive definite matrices given by matrix[i][j], j >= i."""
    p = len(matrix)
    lower = [[None] * p for _ in range(p)]
    for j in range(p):
        lower[j][j] = np.sqrt(matrix[j][j] - sum(lower[j][k] ** 2 for k in range(j)))
        for i in range(j + 1, p):
            lower[i][j] = (matrix[j][i] - sum(lower[i][k] * lower[j][k] for k in range(j))) / lower[j][j]
    return lower


def _forward(lower: list, rhs: list) -> list:
    """z with L z = rhs."""
    z = []
    for i in range(len(rhs)):
        z.append((rhs[i] - sum(lower[i][k] * z[k] for k in range(i))) / lower[i][i])
    return z


def _backward(lower: list, z: list) -> list:
    """x with L^T x = z."""
    p = len(z)
    x = [None] * p
    for i in reversed(range(p)):
        x[i] = (z[i] - sum(lower[k][i] * x[k] for k in range(i + 1, p))) / lower[i][i]
    return x


def _with_ridge(matrix: list, prior: np.ndarray) -> list:
    """matrix + (prior + NUMERICAL_RIDGE max diagonal) I; prior (grey/px)^2 (the prior's precision times s^2)."""
    ridge = prior + NUMERICAL_RIDGE * np.max([matrix[i][i] for i in range(len(matrix))], axis=0)
    return [[entry + ridge if i == j else entry for j, entry in enumerate(row)] for i, row in enumerate(matrix)]


def _translation_covariance(lower: list, m: int) -> np.ndarray:
    """(..., 3) entries xx, xy, yy of the translation block (indices 0 and m) of N^-1, N = L L^T."""
    p = len(lower)
    shape = lower[0][0].shape
    columns = []
    for i in (0, m):
        unit = [np.full(shape, float(k == i)) for k in range(p)]
        columns.append(_forward(lower, unit))  # L^-1 e_i: (N^-1)_ij = (L^-1 e_i) . (L^-1 e_j)
    x, y = columns
    return np.stack((sum(a * a for a in x), sum(a * b for a, b in zip(x, y)), sum(b * b for b in y)), axis=-1)


def _normal_equations(sums: np.ndarray, lay: _Layout, model: str) -> tuple[list, list]:
    """Each node's window system, both supports: matrix[i][j] (j >= i) and rhs[i], each (2, hn, wn).

    sums: (hn, wn, 10) block sums of w g_x g_x, w g_x g_y, w g_y g_y, w g_x y,
    w g_y y, each as (dominant, non-dominant). The basis is
    P(d) = [phi(d), 0; 0, phi(d)], phi the monomials of d / (side / 2).
    """
    monomials = _MONOMIALS[model]
    m = len(monomials)
    orders = sorted({(ai + aj, bi + bj) for ai, bi in monomials for aj, bj in monomials})
    moments = _window_sums(sums, lay, orders)
    for order in moments:  # each float32 moment is let go as soon as its float64 copy replaces it
        moments[order] = np.ascontiguousarray(np.moveaxis(moments[order], 2, 0), np.float64)  # (10, hn, wn)
    product = {(0, 0): 0, (0, 1): 2, (1, 0): 2, (1, 1): 4}  # g_c g_c' -> first channel of its support pair
    matrix = [[None] * (2 * m) for _ in range(2 * m)]
    rhs = [None] * (2 * m)
    for i, (ai, bi) in enumerate(monomials):
        for c in (0, 1):
            rhs[c * m + i] = moments[ai, bi][6 + 2 * c : 8 + 2 * c]
        for j, (aj, bj) in enumerate(monomials):
            for ci in (0, 1):
                for cj in (0, 1):
                    if ci * m + i <= cj * m + j:
                        channel = product[ci, cj]
                        matrix[ci * m + i][cj * m + j] = moments[ai + aj, bi + bj][channel : channel + 2]
    return matrix, rhs
