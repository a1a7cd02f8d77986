"""Exact ground truth of a scene (positions, visibility) and the choice of its query points."""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.frames.synthetic.affine import _apply, _invert
from condtrack_cli.frames.synthetic.layers import _grid, _Layer

BORDER_MARGIN = 16  #: a query lies at least this many pixels inside the frame
EDGE_MARGIN = 8  #: ... and this many pixels away from any layer outline


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


