"""STK baseline: Shi-Tomasi-Kanade, i.e. OpenCV's pyramidal Lucas-Kanade.

Each frame, every point is moved by ``cv2.calcOpticalFlowPyrLK`` from its last
estimate, then tracked back; when the forward-backward distance exceeds
``fb_threshold`` (or LK fails either way) the point is not visible and keeps its
last estimate as its position. STK has no covariance: ``cov`` is NaN.
"""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.filters.base import Tracker
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.filters.settings import STKSettings
from condtrack_cli.types import Frame, Queries, SequenceInfo


def lucas_kanade(prev: np.ndarray, cur: np.ndarray, xy: np.ndarray, settings: STKSettings) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal LK of (P, 2) points from ``prev`` to ``cur`` (uint8 frames): (P, 2) float64, (P,) bool ok."""
    points = xy.astype(np.float32).reshape(-1, 1, 2)
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        prev, cur, points, None,
        winSize=(settings.win_size, settings.win_size), maxLevel=settings.levels - 1,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, settings.max_iterations, settings.epsilon),
        minEigThreshold=settings.min_eig_threshold,
    )
    return moved.reshape(-1, 2).astype(np.float64), status.reshape(-1).astype(bool)


class STKTracker(Tracker):
    method = "stk"

    def __init__(self, settings: STKSettings, queries: Queries, info: SequenceInfo):
        super().__init__(queries, info)
        self.settings = settings

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion | None) -> None:
        start = self.xy[index]
        forward, ok_forward = lucas_kanade(prev.image, frame.image, start, self.settings)
        back, ok_back = lucas_kanade(frame.image, prev.image, forward, self.settings)
        fb_distance = np.linalg.norm(back - start.astype(np.float32), axis=1)
        ok = ok_forward & ok_back & (fb_distance <= self.settings.fb_threshold)
        self.xy[index] = np.where(ok[:, None], forward, start)
        self.visible[index] = ok


def make_stk(settings: STKSettings, queries: Queries, info: SequenceInfo, **_context) -> STKTracker:
    return STKTracker(settings, queries, info)
