"""The plain OpenCV Lucas-Kanade script that condtrack's speed is measured against (issue 13).

What a user would write instead of condtrack, run as a file so that it imports
only numpy and OpenCV: ``python plain_lk.py FRAMES QUERIES OUT.csv [THREADS]``
(THREADS: OpenCV's thread count, its default otherwise). It reads
every image of the folder FRAMES in name order as grey levels, tracks each
point of QUERIES (CSV ``point_id,frame,x,y``) from its query frame on with
``cv2.calcOpticalFlowPyrLK`` (winSize 21, maxLevel 3, 30 iterations or
0.01 px) frame to frame with a forward-backward check of ``FB_THRESHOLD`` px,
and writes ``point_id,frame,x,y,visible`` rows. :mod:`opencv_lk` scores the
same tracker with condtrack's frame reader.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

WIN_SIZE = 21
MAX_LEVEL = 3
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
FB_THRESHOLD = 1.0
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def flow(first: np.ndarray, second: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """LK from ``first`` to ``second`` of (n, 2) float32 ``xy``: (n, 2) positions and (n,) converged flags."""
    moved, status, _ = cv2.calcOpticalFlowPyrLK(
        first, second, xy.reshape(-1, 1, 2), None, winSize=(WIN_SIZE, WIN_SIZE), maxLevel=MAX_LEVEL, criteria=CRITERIA,
    )
    return moved.reshape(-1, 2), status.ravel() == 1


def track_step(prev: np.ndarray, image: np.ndarray, start: np.ndarray,
               fb_threshold: float = FB_THRESHOLD) -> tuple[np.ndarray, np.ndarray]:
    """(n, 2) positions on ``image`` of (n, 2) float32 ``start`` on ``prev`` and (n,) visible flags.

    A point moves to the forward result when the forward pass converged (else it
    stays); it is visible when both directions converged and the backward track
    returns within ``fb_threshold`` px of ``start``.
    """
    forward, ok_forward = flow(prev, image, start)
    back, ok_back = flow(image, prev, forward)
    returned = np.linalg.norm(back - start, axis=1) <= fb_threshold
    return np.where(ok_forward[:, None], forward, start), ok_forward & ok_back & returned


def main(frames: str, queries: str, out: str) -> None:
    rows = np.loadtxt(queries, delimiter=",", skiprows=1, ndmin=2)
    point_id, query_frame = rows[:, 0].astype(int), rows[:, 1].astype(int)
    current = rows[:, 2:4].astype(np.float32)
    paths = sorted(p for p in Path(frames).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    lines = ["point_id,frame,x,y,visible"]
    prev = None
    for k, path in enumerate(paths):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        active = np.flatnonzero(query_frame < k)
        visible = np.zeros(len(rows), bool)
        if prev is not None and active.size:
            current[active], visible[active] = track_step(prev, image, current[active])
        visible[query_frame == k] = True
        shown = np.flatnonzero(query_frame <= k)
        lines += [f"{point_id[i]},{k},{current[i, 0]:.4f},{current[i, 1]:.4f},{int(visible[i])}" for i in shown]
        prev = image
    Path(out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    if len(sys.argv) > 4:  # an optional thread count: the comparison pinned to one thread
        cv2.setNumThreads(int(sys.argv[4]))
    main(*sys.argv[1:4])
