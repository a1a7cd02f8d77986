"""Block matching and sequential RANSAC: starts for the robust motion regression.

Used on the coarsest pyramid level by ``robust.py``. The gradient-based
regression only converges from a start near the answer, and when a strongly
textured object covers much of the frame it can settle between the object's
motion and the background's. Block displacements, found by exhaustive search
with no prior guess, give each block one vote whatever its contrast, so they
propose the motions that most of the frame follows.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Side of the matched blocks (px of the level matched).
BLOCK = 8


def block_displacements(prev: np.ndarray, cur: np.ndarray, radius: int, min_gradient: float,
                        support: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Translation of each BLOCK x BLOCK block of ``prev`` into ``cur`` by exhaustive SSD search.

    prev, cur: (h, w) float32 grey of one level; support: (h, w) bool or None.
    Whole shifts up to ``radius`` px each way are tried and the best is refined
    by a parabola through the SSD minimum (bias < 0.1 px on smooth images).
    Returns the centres and displacements, each (M, 2) px of that level, of the
    M blocks with a clear minimum: strictly inside the search window (so blocks
    moving up to radius - 1/2 px are found), SSD curvature in x and in y at
    least that of a block with gradient ``min_gradient`` grey/px, and at least
    half inside ``support``.
    """
    height, width = prev.shape
    rows, cols = (height - 2 * radius) // BLOCK, (width - 2 * radius) // BLOCK
    if radius < 1 or rows < 1 or cols < 1:
        return np.zeros((0, 2)), np.zeros((0, 2))
    window = np.s_[radius : radius + rows * BLOCK, radius : radius + cols * BLOCK]
    reference = np.ascontiguousarray(prev[window])
    cur = np.ascontiguousarray(cur)
    mask = np.ones_like(reference) if support is None else support[window].astype(np.float32)
    side = 2 * radius + 1
    ssd = np.empty((side, side, rows, cols))  # block-mean squared difference per shift (dy, dx)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            moved = cur[radius + dy : radius + dy + rows * BLOCK, radius + dx : radius + dx + cols * BLOCK]
            squared = mask * np.square(moved - reference)
            ssd[dy + radius, dx + radius] = cv2.resize(squared, (cols, rows), interpolation=cv2.INTER_AREA)
    best_y, best_x = np.divmod(ssd.reshape(side * side, rows, cols).argmin(axis=0), side)
    interior = (best_x > 0) & (best_x < side - 1) & (best_y > 0) & (best_y < side - 1)
    block_rows, block_cols = np.nonzero(interior)
    by, bx = best_y[interior], best_x[interior]
    centre = ssd[by, bx, block_rows, block_cols]
    left, right = ssd[by, bx - 1, block_rows, block_cols], ssd[by, bx + 1, block_rows, block_cols]
    up, down = ssd[by - 1, bx, block_rows, block_cols], ssd[by + 1, bx, block_rows, block_cols]
    curvature_x, curvature_y = left - 2 * centre + right, up - 2 * centre + down
    covered = cv2.resize(mask, (cols, rows), interpolation=cv2.INTER_AREA)[block_rows, block_cols]
    curvature_floor = max(2 * min_gradient**2, 1e-9)  # mean SSD curvature ~ 2 mean(g^2) per px^2 of shift
    clear = (np.minimum(curvature_x, curvature_y) >= curvature_floor) & (covered >= 0.5)
    moves = np.column_stack((
        bx[clear] - radius + (left - right)[clear] / (2 * curvature_x[clear]),
        by[clear] - radius + (up - down)[clear] / (2 * curvature_y[clear]),
    ))
    centres = radius + BLOCK * np.column_stack((block_cols[clear], block_rows[clear])) + (BLOCK - 1) / 2
    return centres, moves


def block_hypotheses(basis: np.ndarray, moves: np.ndarray, inlier_distance: float,
                     trials: int = 200) -> list[np.ndarray]:
    """Up to two (p,) thetas with basis @ theta ~ moves on two groups of blocks (sequential RANSAC).

    basis: (M, 2, p) P(x) at the block centres; moves: (M, 2) displacements;
    inlier_distance in the same unit. The model through each of ``trials``
    minimal sets of blocks (fixed seed: deterministic; Fischler & Bolles 1981)
    counts the blocks within ``inlier_distance``; the best is refitted by least
    squares on its inliers, then the best on the blocks it leaves. The second is
    kept because a strongly textured object can gather more clear blocks than a
    background with flat areas; the caller lets the pixels decide.
    """
    count, _, p = basis.shape
    minimal = p // 2  # each block gives two equations
    if count < p:
        return []
    picks = np.random.default_rng(0).integers(0, count, (trials, minimal))
    system = basis[picks].reshape(trials, 2 * minimal, p)
    ridge = 1e-9 * np.eye(p)  # a repeated or collinear pick gives a useless model, not an error
    gram = system.transpose(0, 2, 1) @ system + ridge
    rhs = system.transpose(0, 2, 1) @ moves[picks].reshape(trials, 2 * minimal, 1)
    hypotheses = np.linalg.solve(gram, rhs)[:, :, 0]  # (T, p)
    predicted = (basis.reshape(-1, p) @ hypotheses.T).T.reshape(trials, count, 2)
    close = np.linalg.norm(moves - predicted, axis=2) < inlier_distance  # (T, M)
    unexplained = np.ones(count, bool)
    thetas = []
    for _ in range(2):
        inliers = close[np.argmax((close & unexplained).sum(axis=1))] & unexplained
        if inliers.sum() < minimal:
            break
        thetas.append(np.linalg.lstsq(basis[inliers].reshape(-1, p), moves[inliers].ravel(), rcond=None)[0])
        unexplained &= ~inliers
    return thetas
