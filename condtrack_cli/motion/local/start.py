"""The local field's start on the coarsest level: block matching of each node's window around the global motion."""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.motion.local.level import _Level
from condtrack_cli.motion.local.windows import _Layout, _window_sums

#: The coarsest level's block-matching start moves a node only where its best
#: shift's cost is under this fraction of the cost without a shift.
SEARCH_GAIN = 0.5

#: Most pixels of shifted frames per batch of the block-matching start (bounds its temporaries, ~40 B a pixel).
SEARCH_BATCH_PIXELS = 2**18


class _SearchBatch:
    """Work arrays of one batch of shifts of the block-matching start on one level layout (``_shift_costs``)."""

    def __init__(self, lay: _Layout):
        rows, cols = lay.padded
        node_rows, node_cols = lay.node_shape
        self.size = size = max(1, SEARCH_BATCH_PIXELS // (rows * cols))  # shifts per batch
        self.positions = np.empty((size, rows, cols, 2), np.float32)
        self.warped = np.empty((size * rows, cols), np.float32)
        self.valid = np.empty((size, rows, cols), np.float32)
        self.difference = np.empty((size, rows, cols), np.float32)
        self.squares = np.empty((size, rows, cols), np.float32)
        self.merged = np.empty((size * rows, cols, 3), np.float32)
        # each shift's block sums and blocks - 1 rows of zeros below them; only the block sums are ever written
        self.sums = np.zeros((size, node_rows + lay.blocks - 1, node_cols, 3), np.float32)


def _searched_start(level: _Level, radius: int) -> np.ndarray:
    """(hn, wn, 4) float32 residual translation (full-resolution px) each node starts from on the coarsest level.

    Block matching of each node's window over integer shifts up to ``radius``
    level px from the global motion (both supports get the same start). The
    cost of a shift is the zero-mean SSD per pixel of the window (a brightness
    offset between the frames is not motion), over pixels landing inside frame
    k, at least half the window. A node keeps the shift of least cost (the
    first in raster order of (dy, dx) on a tie) where that cost is under
    SEARCH_GAIN times the unshifted one, else 0: on weak texture every shift
    costs about the same and the global motion is the better start. The starts
    are then median-filtered over 3 x 3 nodes. The shifts are evaluated in
    batches (``_shift_costs``): a shift of a small coarsest level is too little
    work per OpenCV or numpy call.
    """
    lay = level.lay
    side = 2 * radius + 1
    shifts = np.stack(np.meshgrid(np.arange(-radius, radius + 1), np.arange(-radius, radius + 1)), -1)
    shifts = shifts.reshape(-1, 2).astype(np.float32)  # (dx, dy), dy-major
    if level.work.search is None:
        level.work.search = _SearchBatch(lay)
    batch = level.work.search.size
    best_cost = np.full(lay.node_shape, np.inf)
    best = np.zeros(lay.node_shape + (2,), np.float32)
    reference = np.ascontiguousarray(level.cur[:, :, 0])
    for first in range(0, len(shifts), batch):
        costs = _shift_costs(level, reference, shifts[first : first + batch])
        index = costs.argmin(axis=0)
        cost = np.take_along_axis(costs, index[None], 0)[0]
        better = cost < best_cost
        best_cost = np.where(better, cost, best_cost)
        best[better] = shifts[first + index[better]]
        if first <= radius * side + radius < first + batch:
            unshifted = costs[radius * side + radius - first]
    moved = best_cost < SEARCH_GAIN * unshifted
    start = np.where(moved[:, :, None], best * np.float32(level.factor), np.float32(0))
    start = cv2.medianBlur(start, 3)  # per component over 3 x 3 nodes: an isolated false match does not start a node
    return np.dstack((start, start))


def _shift_costs(level: _Level, reference: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """(S, hn, wn) float64 zero-mean SSD per pixel of each node's window under each of S shifts (S, 2) (level px).

    inf where fewer than half the window's pixels land inside frame k. The S
    (at most ``level.work.search.size``) shifted frames are stacked along the rows,
    and each shift's block sums get blocks - 1 rows of zeros below them, so that
    the window sums of one shift see zeros beyond its own blocks as they would
    alone (BORDER_CONSTANT).
    """
    lay, batch = level.lay, level.work.search
    height, width = lay.shape
    rows, cols = lay.padded
    count = len(shifts)
    positions = np.add(level.base[None], shifts[:, None, None, :], out=batch.positions[:count])
    positions = positions.reshape(count * rows, cols, 2)
    warped = cv2.remap(reference, positions, None, cv2.INTER_LINEAR, dst=batch.warped[: count * rows],
                       borderMode=cv2.BORDER_REPLICATE)
    valid = batch.valid[:count]
    np.copyto(valid.reshape(count * rows, cols), cv2.inRange(positions, (0, 0), (width - 1, height - 1)),
              casting="unsafe")
    valid /= 255
    valid[:, height:], valid[:, :, width:] = 0, 0  # the padding
    difference = np.subtract(warped.reshape(count, rows, cols), level.intensity, out=batch.difference[:count])
    difference *= valid
    squares = np.multiply(difference, difference, out=batch.squares[:count])
    planes = [plane.reshape(count * rows, cols) for plane in (difference, squares, valid)]
    summed = cv2.merge(planes, batch.merged[: count * rows])
    block = lay.block
    if block > 1:
        summed = cv2.resize(summed, (cols // block, count * rows // block), interpolation=cv2.INTER_AREA)
    node_rows, node_cols = lay.node_shape
    sums = batch.sums[:count]
    sums[:, : rows // block, : cols // block] = summed.reshape(count, rows // block, cols // block, 3)
    sums[:, : rows // block, : cols // block] *= block**2
    windows = _window_sums(sums.reshape(-1, node_cols, 3), lay, ((0, 0),))[0, 0]
    windows = windows.reshape(count, -1, node_cols, 3)[:, :node_rows].astype(np.float64)
    total, square_sum, valid_count = windows[..., 0], windows[..., 1], windows[..., 2]
    enough = 0.5 * lay.side**2
    pixels = np.maximum(valid_count, 1)
    return np.where(valid_count >= enough, (square_sum - total**2 / pixels) / pixels, np.inf)
