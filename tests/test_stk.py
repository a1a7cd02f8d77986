"""STK: the tracker reproduces OpenCV's pyramidal LK and flags forward-backward failures."""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.filters.stk import STKSettings, STKTracker
from condtrack_cli.types import Frame, Queries, SequenceInfo

from conftest import translate


def _run(frames, xy, settings):
    queries = Queries(np.arange(len(xy)), np.zeros(len(xy), np.int64), xy)
    tracker = STKTracker(settings, queries, SequenceInfo("mem", frames[0].shape[1], frames[0].shape[0], len(frames), 0))
    prev, out = None, []
    for k, image in enumerate(frames):
        frame = Frame(k, image)
        out.append(tracker.step(frame, prev, None))  # STK estimates its own motion
        prev = frame
    return out


def test_stk_equals_opencv_lucas_kanade(photo):
    frames = [photo, translate(photo, 2.3, -1.2)]
    xy = cv2.goodFeaturesToTrack(photo, 50, 0.01, 10).reshape(-1, 2).astype(np.float64)
    settings = STKSettings(win_size=15, levels=2)
    result = _run(frames, xy, settings)[1]
    expected, status, _ = cv2.calcOpticalFlowPyrLK(
        frames[0], frames[1], xy.astype(np.float32).reshape(-1, 1, 2), None, winSize=(15, 15), maxLevel=1,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01), minEigThreshold=1e-4,
    )
    ok = result.visible
    assert ok.mean() > 0.9
    np.testing.assert_array_equal(result.xy[ok], expected.reshape(-1, 2)[ok].astype(np.float64))
    assert np.isnan(result.cov).all()
    errors = np.linalg.norm(result.xy[ok] - (xy[ok] + [2.3, -1.2]), axis=1)
    assert np.median(errors) < 0.1


def test_failed_forward_backward_check_keeps_the_last_position(photo):
    rng = np.random.default_rng(3)
    noise = rng.integers(0, 256, photo.shape, dtype=np.uint8)  # the scene is replaced: LK cannot be consistent
    xy = cv2.goodFeaturesToTrack(photo, 40, 0.01, 10).reshape(-1, 2).astype(np.float64)
    result = _run([photo, noise], xy, STKSettings())[1]
    lost = ~result.visible
    assert lost.mean() > 0.8
    np.testing.assert_array_equal(result.xy[lost], xy[lost])
