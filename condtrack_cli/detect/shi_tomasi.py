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

from condtrack_cli.registry import register
from condtrack_cli.settings import StageSettings


class ShiTomasiSettings(StageSettings):
    frame_windows = ("block",)
    max_points: int = Field(300, ge=1, description="most points detected on the first frame")
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


def structure_tensor_maps(gray: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c), each (H, W) float32: the block-mean structure tensor [[a, b], [b, c]] at every pixel, (grey/px)^2."""
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    size = (block, block)
    a = cv2.boxFilter(gx * gx, -1, size, borderType=cv2.BORDER_REFLECT)
    b = cv2.boxFilter(gx * gy, -1, size, borderType=cv2.BORDER_REFLECT)
    c = cv2.boxFilter(gy * gy, -1, size, borderType=cv2.BORDER_REFLECT)
    return a, b, c


def min_eigenvalue_map(gray: np.ndarray, block: int) -> np.ndarray:
    """(H, W) float32 smaller eigenvalue of the block-mean structure tensor, (grey/px)^2."""
    a, b, c = structure_tensor_maps(gray, block)
    return (a + c) / 2 - np.sqrt(((a - c) / 2) ** 2 + b * b)


def _nearest(gray: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the pixels nearest (P, 2) positions, clipped to the frame."""
    cols = np.clip(np.rint(xy[:, 0]).astype(int), 0, gray.shape[1] - 1)
    rows = np.clip(np.rint(xy[:, 1]).astype(int), 0, gray.shape[0] - 1)
    return rows, cols


def structure_tensors_at(gray: np.ndarray, xy: np.ndarray, block: int) -> np.ndarray:
    """(P, 2, 2) float64 block-mean structure tensors at (P, 2) positions (nearest pixel), (grey/px)^2."""
    rows, cols = _nearest(gray, xy)
    a, b, c = (m[rows, cols].astype(np.float64) for m in structure_tensor_maps(gray, block))
    return np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2)


def scores_at(gray: np.ndarray, xy: np.ndarray, block: int) -> np.ndarray:
    """(P,) float64 Shi-Tomasi score, (grey/px)^2: the smaller eigenvalue of the block-mean structure tensor
    (:func:`min_eigenvalue_map`) at each (P, 2) position of a (H, W) float32 frame, read at the nearest pixel."""
    rows, cols = _nearest(gray, xy)
    return min_eigenvalue_map(gray, block)[rows, cols].astype(np.float64)


def trackable(gray: np.ndarray, xy: np.ndarray, block: int, floor: float) -> np.ndarray:
    """(P,) bool: the Shi-Tomasi score (:func:`scores_at`) at each (P, 2) position exceeds ``floor``."""
    return scores_at(gray, xy, block) > floor


@register("detect", "shi_tomasi", ShiTomasiSettings, "Shi-Tomasi corners that pass the trackability test")
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
