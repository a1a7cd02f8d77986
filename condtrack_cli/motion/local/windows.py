"""The local field's windows: residual model per level, node and block layout, global flow, window sums.

Each pyramid level's windows sit on a grid of nodes, one per block of pixels;
a window's moments are recombined from the block sums it covers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from condtrack_cli.motion.model import MotionFit, warp_maps
from condtrack_cli.motion.robust import RobustMotionSettings

#: Shortest side (px) of the coarsest level of the local pyramid.
MIN_LOCAL_SIDE = 32

#: Smallest window side on a level (level px): coarse levels widen the window rather than go below it.
MIN_WINDOW = 8

#: Blocks per window side K on the finest level and on coarser ones (one node per block).
FINEST_BLOCKS = 8
COARSE_BLOCKS = 4

#: Warp + IRLS passes on the finest level and on each coarser one.
FINEST_PASSES = 2
COARSE_PASSES = 3

#: Prior std (px) of each residual-motion parameter: keeps every window's system
#: invertible; Q_k reaches about its square where the window has no texture.
RESIDUAL_PRIOR_STD = 16.0

#: Basis monomials (a, b) of (d_x/h)^a (d_y/h)^b, per motion component, of each local model.
_MONOMIALS = {"translation": ((0, 0),), "affine": ((0, 0), (1, 0), (0, 1))}


def local_model(settings: RobustMotionSettings, level: int) -> str:
    """The window's residual model on pyramid level ``level``: 'translation' (p=2) or 'affine' (p=6).

    Affine on the finest level unless ``settings.model`` is 'translation';
    translation on coarser levels, which only need to land in its basin.
    """
    return "affine" if level == 0 and settings.model != "translation" else "translation"


def local_levels(shape: tuple[int, int], levels: int) -> int:
    """``levels`` capped so that the coarsest level's shorter side is >= MIN_LOCAL_SIDE px."""
    return min(levels, 1 + max(0, int(np.log2(min(shape) / MIN_LOCAL_SIDE))))


def passes(level: int) -> int:
    """Warp + IRLS passes on pyramid level ``level`` (0: full resolution)."""
    return FINEST_PASSES if level == 0 else COARSE_PASSES


@dataclass(frozen=True)
class _Layout:
    """Windows of one pyramid level of ``shape`` (h, w) px.

    Pixels are summed over blocks of ``block`` px (block (i, j) covers rows
    i B .. i B + B - 1, columns j B .. j B + B - 1); a window is ``blocks`` x
    ``blocks`` blocks (side K B px); there is one node per block. Node (i, j)
    sits at level position (origin + j B, origin + i B) and its window covers
    the pixels s with -side/2 <= s - node < side/2.
    """

    level: int
    block: int
    blocks: int
    shape: tuple[int, int]

    @property
    def side(self) -> int:
        return self.block * self.blocks

    @property
    def origin(self) -> float:
        return (self.block - 1) / 2 - (self.blocks % 2 == 0) * self.block / 2

    @property
    def padded(self) -> tuple[int, int]:
        """(h, w) rounded up to whole blocks: the shape of the level's work arrays."""
        return tuple(-(-n // self.block) * self.block for n in self.shape)

    @property
    def node_shape(self) -> tuple[int, int]:
        """Nodes (blocks) per column and row: enough to hold every pixel and reach the last one."""
        return tuple(int(np.ceil((n - 1 - self.origin) / self.block)) + 1 for n in self.shape)

    def offsets(self) -> np.ndarray:
        """(K,) position of each block's centre relative to its window's centre (level px)."""
        return (np.arange(self.blocks) - (self.blocks - 1) / 2) * self.block

    def node_positions(self) -> np.ndarray:
        """(rows, columns, 2) full-resolution positions of the nodes (px)."""
        rows, cols = self.node_shape
        return 2**self.level * np.dstack(np.meshgrid(self.origin + self.block * np.arange(cols),
                                                     self.origin + self.block * np.arange(rows)))

    def maps_to(self, shape: tuple[int, int], level: int) -> np.ndarray:
        """(h, w, 2) float32 node coordinates of the pixels of a level (h, w) of pyramid level ``level``."""
        height, width = shape
        scale = 2.0 ** (level - self.level)
        maps = np.empty((height, width, 2), np.float32)
        maps[:, :, 0] = (scale * np.arange(width) - self.origin) / self.block
        maps[:, :, 1] = ((scale * np.arange(height) - self.origin) / self.block)[:, None]
        return maps


def _layout(settings: RobustMotionSettings, level: int, shape: tuple[int, int]) -> _Layout:
    side = max(settings.local_window / 2**level, MIN_WINDOW)
    block = max(1, round(side / (FINEST_BLOCKS if level == 0 else COARSE_BLOCKS)))
    return _Layout(level, block, max(1, round(side / block)), shape)


def _global_flow(fit: MotionFit, shape: tuple[int, int]) -> np.ndarray:
    """(H, W, 2) float32 U_g(x) of the global fit at every pixel (px)."""
    map_x, map_y = warp_maps(fit.model, fit.theta, fit.origin, fit.length, shape)
    height, width = shape
    map_x -= np.arange(width, dtype=np.float32)
    map_y -= np.arange(height, dtype=np.float32)[:, None]
    return np.dstack((map_x, map_y))


def _interpolate(nodes: np.ndarray, maps: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(h, w, C) float32 bilinear samples of node values (hn, wn, C) at node coordinates ``maps`` (h, w, 2)."""
    sampled = cv2.remap(np.ascontiguousarray(nodes, np.float32), maps, None, cv2.INTER_LINEAR, dst=out,
                        borderMode=cv2.BORDER_REPLICATE)
    return sampled.reshape(maps.shape[:2] + (nodes.shape[2],))


def _window_sums(sums: np.ndarray, lay: _Layout, orders) -> dict:
    """Window moments sum_{s in R} f(s) (d_x / h)^a (d_y / h)^b at the nodes, for the (a, b) in ``orders``.

    sums: (hn, wn, C) block sums of f; d = s - node, h = side / 2. Each pixel
    counts at its block's centre, plus the spread of a block's pixels about it
    ((B^2 - 1) / 12 per axis in order 2). Returns {(a, b): (hn, wn, C)}, dtype of ``sums``.
    """
    offsets = lay.offsets() / (lay.side / 2)
    anchor = lay.blocks // 2
    along_x = {a: cv2.filter2D(sums, -1, offsets[None] ** a, anchor=(anchor, 0), borderType=cv2.BORDER_CONSTANT)
               for a in {a for a, _ in orders}}
    moments = {(a, b): cv2.filter2D(along_x[a], -1, offsets[:, None] ** b, anchor=(0, anchor),
                                    borderType=cv2.BORDER_CONSTANT).reshape(sums.shape) for a, b in orders}
    spread = (lay.block**2 - 1) / 12 / (lay.side / 2) ** 2
    for order in ((2, 0), (0, 2)):
        if order in moments:
            moments[order] = moments[order] + spread * moments[0, 0]
    return moments
