"""The Lucas-Kanade fallback gate centre (``lk_fallback``) and the visibility of an uninformative match as good as the
point's usual ones (``seen_residual``), ``filters/reference.py``; issue 31.

Known truth: frame 1 is frame 0 (a photograph, with noise) moved by (27, -19) px, a jump far beyond the
16 px search square; the filters predict no motion. Without the fallback no point is found at its true
position; with it, every point found on frame 0 is matched again around where pyramidal Lucas-Kanade
moves it and found there, and the prediction moves to that centre (``shift``).
"""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.filters.reference import ReferenceMatcher, lk_centres
from condtrack_cli.filters.settings import MeasuredFilterSettings
from condtrack_cli.measure.response import SSDSettings
from condtrack_cli.measure.ssd import SSDMeasure, searched
from condtrack_cli.types import Frame

from conftest import load_asset

JUMP = np.array([27.0, -19.0])


def _jump_frames() -> tuple[Frame, Frame, np.ndarray]:
    """Frames 0 and 1 (frame 1 = frame 0 moved by JUMP) and (n, 2) textured points of frame 0 well inside both."""
    rng = np.random.default_rng(0)
    photo = load_asset("camera.png").astype(np.float64)
    h, w = 200, 240
    top, left = 60, 60
    crop0 = photo[top : top + h, left : left + w]
    crop1 = photo[top - int(JUMP[1]) : top - int(JUMP[1]) + h, left - int(JUMP[0]) : left - int(JUMP[0]) + w]
    images = [np.clip(c + rng.normal(0, 1.0, c.shape), 0, 255).astype(np.uint8) for c in (crop0, crop1)]
    corners = cv2.goodFeaturesToTrack(images[0], 40, 0.02, 12)[:, 0].astype(np.float64)
    inside = ((corners >= 40) & (corners + JUMP <= [w - 41, h - 41]) & (corners + JUMP >= 40)).all(axis=1)
    inside &= (corners <= [w - 41, h - 41]).all(axis=1)
    return Frame(0, images[0]), Frame(1, images[1]), corners[inside]


def _match(lk_fallback: bool, retry: np.ndarray | None = None, predicted_step: np.ndarray = np.zeros(2)):
    """The points of :func:`_jump_frames` and their measurement on frame 1, predicted moved by ``predicted_step``."""
    frame0, frame1, xy = _jump_frames()
    measure = SSDMeasure(SSDSettings())
    reference = ReferenceMatcher(measure, MeasuredFilterSettings(lk_fallback=lk_fallback), len(xy), 9.21)
    index = np.arange(len(xy))
    reference.start(index, frame0, xy)
    s_pred = np.repeat(np.eye(2)[None], len(xy), 0)
    retry = np.ones(len(xy), bool) if retry is None else retry
    return xy, reference.measure_in_gate(index, frame1, xy + predicted_step, s_pred, frame0, xy, retry)


def test_a_jump_beyond_the_search_square_is_found_around_the_lucas_kanade_centre():
    xy, oracle = _match(False, predicted_step=JUMP)  # the points found where the prediction is right
    assert oracle.valid.sum() >= 5
    np.testing.assert_allclose(oracle.z[oracle.valid], (xy + JUMP)[oracle.valid], atol=0.25)
    xy, off = _match(False)
    assert not np.any(off.valid & (np.linalg.norm(off.z - (xy + JUMP), axis=1) < 2.0))
    assert np.all(off.shift == 0)
    xy, on = _match(True)
    np.testing.assert_array_equal(on.valid, oracle.valid)
    np.testing.assert_allclose(on.z[on.valid], (xy + JUMP)[on.valid], atol=0.25)
    np.testing.assert_allclose(on.shift[on.valid], np.broadcast_to(JUMP, xy.shape)[on.valid], atol=1.0)  # LK's centre
    assert np.all(on.shift[~on.valid] == 0)


def test_only_points_found_before_are_tried():
    xy, found = _match(True)
    retry = np.arange(len(xy)) % 2 == 0
    _, measured = _match(True, retry)
    np.testing.assert_array_equal(measured.valid[retry], found.valid[retry])
    assert not np.any(measured.valid[~retry] & (np.linalg.norm(measured.z[~retry] - (xy[~retry] + JUMP), axis=1) < 2.0))
    assert np.all(measured.shift[~retry] == 0)


def test_lucas_kanade_centres_at_half_resolution_follow_the_jump():
    frame0, frame1, xy = _jump_frames()
    centre, ok = lk_centres(cv2.pyrDown(frame0.image), cv2.pyrDown(frame1.image), xy)
    assert ok.all()
    np.testing.assert_allclose(centre, xy + JUMP, atol=1.0)


def test_searched_is_the_measurement_gate():
    """A candidate the SSD gate holds is 'searched'; one beyond the square or the ellipse is not."""
    settings = SSDSettings()
    predicted = np.array([[50.2, 40.7]] * 4)
    cov = np.array([np.eye(2), np.eye(2), 100 * np.eye(2), np.diag([100.0, 1.0])])
    xy = predicted + np.array([[2.0, 1.0], [5.0, 0.0], [20.0, 0.0], [0.0, 8.0]])
    np.testing.assert_array_equal(searched(predicted, cov, xy, settings), [True, False, False, False])
    np.testing.assert_array_equal(searched(predicted, cov, predicted + [[3.0, 0.0], [0, 0], [15.0, 0], [14.0, 0]],
                                           settings), [True, True, True, True])


class _FlatMeasure:
    """A measurement stage whose frame k holds the point at (50, 40) with residual ``residuals[k]``: informative
    (R = 0.5 I) on the frames of ``informative``, a flat surface (R infinite, the same minimum) elsewhere; frame k is
    read from the grey level of its top-left pixel."""

    template_side = 3

    def __init__(self, residuals: dict[int, float], informative: set[int]):
        self.residuals, self.informative = residuals, informative

    def templates(self, gray, xy):
        return np.zeros((len(xy), 3, 3), np.float32)

    def noise_sigma(self, gray):
        return 1.0

    def measure(self, gray, templates, predicted, gate_cov, sigma):
        from condtrack_cli.measure.interface import Measurement

        k, n = int(gray[0, 0]), len(predicted)
        informative = k in self.informative
        R = np.tile(0.5 * np.eye(2) if informative else np.diag([np.inf, np.inf]), (n, 1, 1))
        return Measurement(np.tile((50.0, 40.0), (n, 1)), R, np.full(n, self.residuals[k]), np.full(n, informative))


def test_an_uninformative_match_as_good_as_the_usual_ones_is_seen_not_used():
    """``seen_residual`` (2): frames 1-2 informative matches with residual 10; frame 3 a flat surface whose minimum
    (in the gate) has residual 15 (<= 2 x 10): not used, but seen; frame 4 flat with residual 40 (> 2 x the usual):
    neither (an occluder); frame 5 flat, residual 15, but 30 px from the prediction: outside the gate, not seen.
    With ``seen_residual: null`` nothing uninformative is seen."""
    residuals = {1: 10.0, 2: 10.0, 3: 15.0, 4: 40.0, 5: 15.0}
    measure = _FlatMeasure(residuals, informative={1, 2})
    frames = [Frame(k, np.full((80, 100), k, np.uint8)) for k in range(6)]
    s_pred = np.eye(2)[None]
    for seen_residual, expected in ((2.0, [False, False, True, False, False]), (None, [False] * 5)):
        settings = MeasuredFilterSettings(seen_residual=seen_residual, lk_fallback=False)
        reference = ReferenceMatcher(measure, settings, 1, 9.21)
        reference.start(np.array([0]), frames[0], np.array([[50.0, 40.0]]))
        seen, valid = [], []
        for k in residuals:
            predicted = np.array([[50.0, 40.0]]) if k != 5 else np.array([[80.0, 40.0]])
            m = reference.measure_in_gate(np.array([0]), frames[k], predicted, s_pred)
            seen.append(bool(m.seen[0]))
            valid.append(bool(m.valid[0]))
        assert seen == expected
        assert valid == [True, True, False, False, False]
