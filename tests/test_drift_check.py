"""The drift-checked reference re-take (``drift_check``, issue 45; ``filters/reference.py``) and the re-take walk of
the error model (``filters/calibration.py``).

Known truth: frame 1 is frame 0 (a photograph, with noise) moved by (27, -19) px, so each point's first patch is
found on frame 1 exactly where the point went. An estimate off by 1.8 px re-takes its reference at the estimate
without the check (the patch there is 1.8 px off the point) and at the first patch's match with it.
"""

from __future__ import annotations

import numpy as np
import pytest

from condtrack_cli.filters.calibration import RATIO_WALK, ErrorModel
from condtrack_cli.filters.reference import GatedMeasurement, ReferenceMatcher
from condtrack_cli.filters.settings import MeasuredFilterSettings
from condtrack_cli.measure.response import SSDSettings
from condtrack_cli.measure.ssd import SSDMeasure

from test_fallback import JUMP, _jump_frames

OFF = np.array([1.2, -1.35])  #: the drifted estimate's offset from the point (1.8 px)


def _refresh(drift_check: float | None, offset: np.ndarray,
             first_side: int | None = None) -> tuple[ReferenceMatcher, np.ndarray, np.ndarray]:
    """The matcher after one forced re-take of every point at its true position on frame 1 plus ``offset`` (the first
    patch matched at ``first_side`` px, ``drift_check_template``), the templates the re-take should give at the
    truth, and the points' true positions on frame 1."""
    frame0, frame1, xy = _jump_frames()
    measure = SSDMeasure(SSDSettings())
    settings = MeasuredFilterSettings(drift_check=drift_check, drift_check_template=first_side)
    matcher = ReferenceMatcher(measure, settings, len(xy), 9.21)
    index = np.arange(len(xy))
    matcher.start(index, frame0, xy)
    truth = xy + JUMP
    n = len(xy)
    # a match used on both frames whose residual is far above the refresh's bound: every point is re-taken
    measured = GatedMeasurement(z=truth, R=np.repeat(np.eye(2)[None], n, 0), R_used=np.repeat(np.eye(2)[None], n, 0),
                                valid=np.ones(n, bool), residual=np.full(n, 1e12), shown=np.ones(n, bool),
                                shift=np.zeros((n, 2)), jump=np.zeros((n, 2)))
    retaken = matcher.refresh(index, frame0, xy, frame1, truth + offset, np.ones(n, bool), measured)
    assert retaken.all()
    return matcher, measure.templates(frame1.gray, truth), truth


def _template_error(matcher: ReferenceMatcher, expected: np.ndarray) -> np.ndarray:
    """(n,) mean absolute grey-level difference of the re-taken templates from ``expected``."""
    return np.abs(matcher.templates - expected).mean(axis=(1, 2))


def test_a_drifted_estimate_re_takes_its_reference_where_the_first_patch_matches():
    """With the check every re-take lands on the point: within 2 grey levels of the patch at the truth (noise 1,
    sub-pixel interpolation), with the two positions' disagreement as the offset's floor; without it the patch 1.8 px
    off differs by more than 5 grey levels on most points."""
    checked, at_truth, _ = _refresh(3.0, OFF)
    assert len(at_truth) >= 5
    assert (_template_error(checked, at_truth) < 2.0).all()
    # confirmed by the first patch: the chain and the first patch disagree by the 1.8 px offset, the floor is that
    # disk's per-axis variance r^2 / 4 (the match is sub-pixel: within 10 %)
    np.testing.assert_allclose(checked.offset_floor, (OFF**2).sum() / 4, rtol=0.1)
    unchecked, _, _ = _refresh(None, OFF)
    assert np.median(_template_error(unchecked, at_truth)) > 5.0


def test_a_wider_first_patch_is_taken_at_the_query_and_finds_the_point_too():
    """``drift_check_template`` 21: the first patch the check matches is the 21 px patch at the query (the 11 px
    reference's is kept for the re-acquisition), and the drifted estimate's re-take lands on the point as with the
    11 px one, within 2 grey levels, with the same floor."""
    wide, at_truth, _ = _refresh(3.0, OFF, first_side=21)
    frame0, _, xy = _jump_frames()
    assert wide.drift_anchors.shape == (len(xy), 21, 21) and wide.anchors.shape == (len(xy), 11, 11)
    np.testing.assert_array_equal(wide.drift_anchors, wide.anchor_measure.templates(frame0.gray, xy))
    assert (_template_error(wide, at_truth) < 2.0).all()
    np.testing.assert_allclose(wide.offset_floor, (OFF**2).sum() / 4, rtol=0.1)


def test_the_first_patch_side_is_the_reference_s_unless_set_and_odd():
    """Unset (the default) the check matches the reference's own first patch, the same array; a resized stage is
    made once per side and shared; an even side is refused."""
    default, _, _ = _refresh(3.0, OFF)
    assert default.drift_anchors is default.anchors and default.anchor_measure is default.measure
    measure = SSDMeasure(SSDSettings())
    assert measure.resized(21) is measure.resized(21) and measure.resized(21).template_side == 21
    assert measure.resized(11) is measure
    with pytest.raises(ValueError, match="must be odd"):
        MeasuredFilterSettings(drift_check_template=20)


def test_a_re_take_the_first_patch_does_not_confirm_gets_the_check_s_reach_as_a_floor():
    """An estimate 6 px off: the first patch's match lies beyond the 3 px reach, so the re-take stays at the estimate
    and nothing holds its offset below the reach: a floor of 3^2 / 4 px^2 per axis for the error model."""
    far, at_truth, truth = _refresh(3.0, 5 * OFF)
    assert np.median(_template_error(far, at_truth)) > 5.0
    np.testing.assert_array_equal(far.offset_floor, 2.25)


def test_the_re_take_walk_sets_the_scale_of_the_student_t_not_only_its_tail():
    """A point found on every frame whose reference was re-taken unconfirmed (floor 9 px^2 here): its reported covariance
    holds the floor on both axes from the next frame on (the new reference measures the frames after it), and the
    Student-t's scale is RATIO_WALK of it (a steady offset, not a rare jump)."""
    model = ErrorModel(1, 9.21)
    index = np.array([0])
    tiny = 1e-4 * np.eye(2)[None]
    model.start(index, tiny)
    zero, found = np.zeros((1, 2)), np.array([True])
    model.update(index, zero, tiny, zero, tiny, found, zero, tiny, found, zero, np.array([9.0]))
    assert np.diag(model.reported[0]).max() < 1.0
    model.update(index, zero, tiny, zero, tiny, found, zero, tiny, ~found, zero, np.array([0.0]))
    assert np.diag(model.reported[0]).min() >= 9.0
    assert model.ratio[0] == pytest.approx(RATIO_WALK, rel=1e-3)
    assert model.dof[0] == pytest.approx(2.0 / (1.0 - RATIO_WALK), rel=1e-3)


def test_a_re_take_the_first_patch_does_not_confirm_is_not_vouched_for():
    """The re-acquisition's first-patch search is centred where the point was last found with a reference its first
    patch vouched for (``vouched_seen``, tests/test_fallback.py): the match of this frame, made with the query's
    reference, is such a place; the reference re-taken 6 px off, beyond the check's reach, is not vouched for, the
    one re-taken at the first patch's match is, and without the check (the paper's re-take at the estimate) every
    re-take is."""
    far, _, truth = _refresh(3.0, 5 * OFF)
    assert not far.vouched.any()
    np.testing.assert_array_equal(far.vouched_seen, truth + 5 * OFF)
    near, _, truth = _refresh(3.0, OFF)
    assert near.vouched.all()
    np.testing.assert_array_equal(near.vouched_seen, truth + OFF)
    unchecked, _, _ = _refresh(None, 5 * OFF)
    assert unchecked.vouched.all()
