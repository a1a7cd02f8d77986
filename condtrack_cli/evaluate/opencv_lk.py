"""The plain OpenCV Lucas-Kanade baseline of issue 11 (what a user would otherwise pick).

``cv2.calcOpticalFlowPyrLK`` with winSize 21, maxLevel 3 (four pyramid levels),
30 iterations or 0.01 px, frame to frame, and a forward-backward check
(:func:`plain_lk.track_step`): a point is visible on frame k when both
directions converged and the backward track returns within ``fb_threshold`` px
of where it started. A point moves to the forward result whenever the forward
pass converged (even when the check fails), and keeps its last position
otherwise. Points are tracked forward from their query frame only (nothing
before it: the 'first' query mode scores nothing there). No covariance. This is deliberately not condtrack's ``stk``
(which keeps the last position when the check fails and tracks backward too):
it is the baseline as a user would write it, scored by the same code.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from condtrack_cli.evaluate.plain_lk import track_step
from condtrack_cli.frames.readers import FrameSettings, open_frames
from condtrack_cli.registry import method_code
from condtrack_cli.types import Queries, Tracks


#: (previous image, image, (n, 2) float32 positions on the previous image) -> ((n, 2) positions, (n,) visible flags).
Step = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def chain_frame_to_frame(folder: str | Path, queries: Queries, step: Step, method: str) -> Tracks:
    """Track ``queries`` through the frames of ``folder`` (read as condtrack reads them) by chaining ``step``.

    Each point starts at its query on its query frame (visible there) and moves
    by ``step`` from each frame to the next, all active points at once.
    Returns Tracks (P, F): positions from each query frame on, NaN before;
    cov NaN, dof inf; every row's method ``method``; z and R NaN.
    """
    frames = open_frames(FrameSettings(), folder)
    p, f = len(queries), frames.info.n_frames
    xy = np.full((p, f, 2), np.nan)
    visible = np.zeros((p, f), bool)
    current = queries.xy.astype(np.float32)
    prev = None
    for k, image in enumerate(frames):
        active = np.flatnonzero(queries.frame < k)
        if prev is not None and active.size:
            current[active], visible[active, k] = step(prev, image, current[active])
            xy[active, k] = current[active]
        new = np.flatnonzero(queries.frame == k)
        xy[new, k], visible[new, k] = queries.xy[new], True
        prev = image
    code = np.where(np.isfinite(xy[..., 0]), method_code(method), -1).astype(np.int8)
    return Tracks(
        queries=queries, xy=xy, cov=np.full((p, f, 2, 2), np.nan), dof=np.where(np.isfinite(xy[..., 0]), np.inf, np.nan),
        visible=visible, method=code,
        z=np.full((p, f, 2), np.nan), R=np.full((p, f, 2, 2), np.nan),
    )


def opencv_lk(folder: str | Path, queries: Queries, fb_threshold: float = 1.0) -> Tracks:
    """Track ``queries`` through the frames of ``folder`` with plain OpenCV LK (:func:`chain_frame_to_frame`).

    Rows' method recorded as ``stk`` (OpenCV's LK).
    """
    return chain_frame_to_frame(folder, queries, partial(track_step, fb_threshold=fb_threshold), "stk")
