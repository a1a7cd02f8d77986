"""The in-process baselines of the bench: OpenCV LK (issue 11) and chained DIS (issue 45)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from condtrack_cli.evaluate.opencv_dis import dis_step, opencv_dis
from condtrack_cli.evaluate.opencv_lk import opencv_lk
from condtrack_cli.registry import method_code
from condtrack_cli.types import Queries

#: Per-frame translation (px) of the test sequence, and its frame count and size (W, H).
SHIFT = np.array([1.25, -0.75])
N_FRAMES, SIZE = 6, (160, 120)


@pytest.fixture(scope="module")
def translation(tmp_path_factory):
    """A folder of N_FRAMES grey frames of a smooth random texture translated by SHIFT px per frame (cubic-spline
    resampled from a larger texture, so frame k at x shows what frame 0 shows at x - k SHIFT)."""
    rng = np.random.default_rng(3)
    texture = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (SIZE[1] + 40, SIZE[0] + 40)), 2.0)
    texture = 128 + 60 * texture / texture.std()
    folder = tmp_path_factory.mktemp("translation")
    for k in range(N_FRAMES):
        dx, dy = k * SHIFT
        moved = ndimage.shift(texture, (dy, dx), order=3, mode="mirror")[20:-20, 20:-20]
        cv2.imwrite(str(folder / f"{k:05d}.png"), np.clip(np.rint(moved), 0, 255).astype(np.uint8))
    return folder


@pytest.mark.parametrize("baseline", [opencv_dis, opencv_lk])
def test_baselines_follow_a_translation_from_each_query_frame(translation, baseline):
    """Points queried on frames 0 and 2 are followed within 0.2 px of the exact translation on every later frame,
    visible there, and have no position before their query frame; no covariance, a Gaussian dof."""
    xy = np.array([[50.0, 60.0], [80.5, 40.25], [110.0, 70.0], [70.0, 80.0]])
    queries = Queries(np.arange(4), np.array([0, 0, 2, 2]), xy)
    tracks = baseline(translation, queries)
    k = np.arange(N_FRAMES)
    truth = xy[:, None] + (k[None, :, None] - queries.frame[:, None, None]) * SHIFT
    after = k[None] >= queries.frame[:, None]
    error = np.linalg.norm(tracks.xy - truth, axis=2)
    assert error[after].max() < 0.2, error
    assert np.isnan(tracks.xy[~after]).all() and not tracks.visible[~after].any()
    assert tracks.visible[after].all()
    assert np.isnan(tracks.cov).all() and np.isinf(tracks.dof[after]).all()
    expected = method_code("mdr" if baseline is opencv_dis else "stk")
    assert (tracks.method[after] == expected).all() and (tracks.method[~after] == -1).all()


class FixedFlow:
    """A stand-in for ``cv2.DISOpticalFlow``: ``calc`` returns the forward field, then the backward one, in turn."""

    def __init__(self, forward: np.ndarray, backward: np.ndarray):
        self.fields = [forward, backward]

    def calc(self, first, second, flow):
        return self.fields.pop(0)


def test_dis_step_samples_the_forward_flow_bilinearly_and_checks_the_round_trip():
    """Forward field u = (0.1 x + 2, 0.05 y), linear (so bilinear sampling is exact, pixel centres at integers):
    points move by it within 1e-4 px. Backward field -(2, 0.05 y') except the right part x' >= 60, where it is 1.5 px
    too short in x: points landing there fail the 1 px round trip, the others pass it."""
    h, w = 50, 80
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    forward = np.dstack([0.1 * xs + 2.0, 0.05 * ys])
    # the backward field at x' undoes the forward step of x = (x' - 2) / 1.1, y = y' / 1.05
    backward = np.dstack([(xs - 2.0) / 1.1 - xs + np.where(xs >= 60, 1.5, 0.0), ys / 1.05 - ys]).astype(np.float32)
    start = np.array([[10.25, 20.5], [30.0, 7.75], [55.5, 30.0], [58.0, 10.0]], np.float32)
    image = np.zeros((h, w), np.uint8)
    moved, visible = dis_step(FixedFlow(forward, backward), image, image, start)
    expected = np.column_stack([1.1 * start[:, 0] + 2.0, 1.05 * start[:, 1]])
    np.testing.assert_allclose(moved, expected, rtol=0, atol=1e-4)
    np.testing.assert_array_equal(visible, expected[:, 0] < 59.0)  # the last two land at x' > 60
    assert visible[:2].all() and not visible[2:].any()
