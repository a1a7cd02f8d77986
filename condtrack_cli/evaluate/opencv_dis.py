"""Chained dense flow, the second baseline of issue 45 (what a user can write in twenty lines).

OpenCV DIS at preset MEDIUM (``cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)``), forward and
backward flow for each consecutive frame pair; a point x on frame k-1 moves to x' = x + F(x) on frame k, F the
forward field sampled bilinearly at x (pixel centres at integer positions, as OpenCV; the field's border
replicated outside the frame). It is visible on frame k when the round trip x' + B(x'), B the backward field
sampled at x', returns within ``fb_threshold`` px of x. A point keeps moving by the forward flow when the check
fails (that is what chaining does): visibility is per frame. Points are tracked forward from their query frame
only, every point at once, as :func:`opencv_lk.opencv_lk` does; no covariance; rows' method recorded as ``mdr``
(motion alone, no measurement).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import cv2
import numpy as np

from condtrack_cli.evaluate.opencv_lk import chain_frame_to_frame
from condtrack_cli.motion.robust import _sample
from condtrack_cli.types import Queries, Tracks


def dis_step(dis: cv2.DISOpticalFlow, prev: np.ndarray, image: np.ndarray, start: np.ndarray,
             fb_threshold: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) float32 positions on ``image`` of (n, 2) float32 ``start`` on ``prev`` (both (H, W) uint8) and
    (n,) visible flags: forward DIS flow sampled at ``start``, round trip through the backward flow within
    ``fb_threshold`` px."""
    forward = _sample(dis.calc(prev, image, None), start)
    moved = start + forward
    back = _sample(dis.calc(image, prev, None), moved)
    return moved, np.linalg.norm(moved + back - start, axis=1) <= fb_threshold


def opencv_dis(folder: str | Path, queries: Queries, fb_threshold: float = 1.0) -> Tracks:
    """Track ``queries`` through the frames of ``folder`` (read as condtrack reads them) by chained DIS MEDIUM.

    Returns Tracks (P, F) as :func:`opencv_lk.opencv_lk` does (positions from each query frame on, NaN before;
    cov NaN), rows' method ``mdr``.
    """
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return chain_frame_to_frame(folder, queries, partial(dis_step, dis, fb_threshold=fb_threshold), "mdr")
