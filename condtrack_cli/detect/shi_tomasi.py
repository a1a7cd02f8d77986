"""Shi-Tomasi corners and the trackability test (Shi & Tomasi 1994; paper §5.3).

The structure tensor of a point is the mean over a ``block`` x ``block`` window of
g g^T, g the image gradient in grey levels per pixel (3x3 Sobel / 8). Its
smaller eigenvalue, in (grey levels / px)^2, says how well the window can be
located in every direction: near zero on a flat region and along an edge, large
on a corner. A point is trackable when it exceeds ``min_eigenvalue``.

The same test is applied to user-given queries (``detect/trackability.py``):
``untrackable`` says what happens to those that fail it.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field

from condtrack_cli.settings import OPENCV_INT_MAX, StageSettings


class ShiTomasiSettings(StageSettings):
    frame_windows = ("block",)
    max_points: int = Field(300, ge=1, le=OPENCV_INT_MAX, description="most points detected on the first frame")
    quality: float = Field(0.01, gt=0, le=1, description="keep corners whose score is at least this fraction of the best")
    min_distance: float = Field(8.0, ge=0, description="least distance between two detected points (px)")
    border: int = Field(16, ge=0, description="no point closer than this to the frame's edge (px)")
    block: int = Field(7, ge=3, le=31, description="side of the structure-tensor window (px, odd)")
    min_eigenvalue: float = Field(
        10.0, ge=0, description="trackability floor on the smaller structure-tensor eigenvalue ((grey/px)^2)"
    )
    untrackable: Literal["keep", "drop", "error"] = Field(
        "keep", description="queries at or below min_eigenvalue: keep (tracked, with a warning), drop (not tracked) or "
        "error (--untrackable)",
    )


#: The 3x3 Sobel derivative across x, [row, col], divided by 8 so that the gradient is in grey levels per pixel.
SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0


def _reflect(index: np.ndarray, size: int, edge_repeated: bool) -> np.ndarray:
    """``index`` folded into [0, size) as OpenCV's borders do: BORDER_REFLECT (``edge_repeated``,
    fedcba|abcdef) or BORDER_REFLECT_101 (edcb|abcdef), repeated as often as a window larger than the frame needs."""
    if not edge_repeated and size == 1:
        return np.zeros_like(index)
    period = 2 * size if edge_repeated else 2 * size - 2
    folded = np.mod(index, period)
    return np.where(folded < size, folded, period - folded - (1 if edge_repeated else 0))


def _nearest(gray: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels nearest (P, 2) positions, clipped to the frame."""
    cols = np.clip(np.rint(xy[:, 0]).astype(int), 0, gray.shape[1] - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int), 0, gray.shape[0] - 1)
    return rows, cols


def structure_tensors_at(gray: np.ndarray, xy: np.ndarray, block: int) -> np.ndarray:
    """(P, 2, 2) float64 block-mean structure tensors at (P, 2) positions (nearest pixel), (grey/px)^2.

    Computed on each point's own window, not on the whole frame: the gradient by the 3x3 Sobel (/ 8) with
    OpenCV's default border (reflect-101), its products averaged over the ``block`` x ``block`` window with
    the border reflected (edge repeated), as ``cv2.Sobel`` then ``cv2.boxFilter(..., BORDER_REFLECT)`` on the
    frame would give them (up to float rounding).
    """
    height, width = gray.shape
    rows, cols = _nearest(gray, xy)
    half = np.arange(block) - block // 2
    taps = np.arange(-1, 2)
    # (P, block, 3): the frame rows (cols) the Sobel reads for each row (col) of each point's window
    sobel_rows = _reflect(_reflect(rows[:, None] + half, height, True)[:, :, None] + taps, height, False)
    sobel_cols = _reflect(_reflect(cols[:, None] + half, width, True)[:, :, None] + taps, width, False)
    patches = gray[sobel_rows[:, :, None, :, None], sobel_cols[:, None, :, None, :]].astype(np.float64)
    gx = np.einsum("pijab,ab->pij", patches, SOBEL_X)  # (P, block, block)
    gy = np.einsum("pijab,ba->pij", patches, SOBEL_X)
    a, b, c = ((u * v).mean(axis=(1, 2)) for u, v in ((gx, gx), (gx, gy), (gy, gy)))
    return np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)


def scores_at(gray: np.ndarray, xy: np.ndarray, block: int) -> np.ndarray:
    """(P,) float64 Shi-Tomasi score, (grey/px)^2: the smaller eigenvalue of the block-mean structure tensor
    (:func:`structure_tensors_at`) at each (P, 2) position of a (H, W) frame, read at the nearest pixel."""
    tensors = structure_tensors_at(gray, xy, block)
    a, b, c = tensors[:, 0, 0], tensors[:, 0, 1], tensors[:, 1, 1]
    return (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b * b)


def trackable(gray: np.ndarray, xy: np.ndarray, block: int, floor: float) -> np.ndarray:
    """(P,) bool: the Shi-Tomasi score (:func:`scores_at`) at each (P, 2) position exceeds ``floor``."""
    return scores_at(gray, xy, block) > floor


def detect_points(settings: ShiTomasiSettings, gray: np.ndarray) -> np.ndarray:
    """(M, 2) float64 corner positions on a (H, W) float32 frame, best first."""
    height, width = gray.shape
    mask = np.zeros((height, width), np.uint8)
    b = settings.border
    mask[b : height - b, b : width - b] = 255
    corners = cv2.goodFeaturesToTrack(
        gray, maxCorners=settings.max_points, qualityLevel=settings.quality,
        minDistance=settings.min_distance, mask=mask, blockSize=settings.block, useHarrisDetector=False,
    )
    if corners is None:
        return np.zeros((0, 2))
    xy = corners.reshape(-1, 2).astype(np.float64)
    return xy[trackable(gray, xy, settings.block, settings.min_eigenvalue)]
