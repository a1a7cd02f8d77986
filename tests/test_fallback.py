"""The fallback gate centres (``lk_fallback``: Lucas-Kanade, the last measured step, a coarse search),
``filters/reference.py``; issue 31 (the visibility of a point too flat to measure, ``flat_visible_residual``:
tests/test_clf.py).

Known truth: frame 1 is frame 0 (a photograph, with noise) moved by (27, -19) px, a jump far beyond the
16 px search square; the filters predict no motion. Without the fallback no point is found at its true
position; with it, every point found on frame 0 is matched again around where pyramidal Lucas-Kanade
moves it and found there, and the prediction moves to that centre (``shift``).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from condtrack_cli.filters.reference import (
    COARSE_REACH,
    COARSE_SIDE,
    REACQUIRE_FIT,
    REACQUIRE_FRAMES,
    REACQUIRE_REACH,
    REACQUIRE_TEXTURE,
    GatedMeasurement,
    HalfFrame,
    ReferenceMatcher,
    coarse_centres,
    coarse_search,
    lk_centres,
)
from condtrack_cli.filters.settings import STEADY_FRAMES, MeasuredFilterSettings
from condtrack_cli.measure.interface import Measurement
from condtrack_cli.measure.response import SSDSettings
from condtrack_cli.measure.ssd import SSDMeasure, searched
from condtrack_cli.measure.surfaces import extract_templates
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


def _started(lk_fallback: bool = True):
    """Frames 0 and 1 and the points of :func:`_jump_frames`, a reference started on them at frame 0, their indices
    and a unit predicted covariance (n, 2, 2)."""
    frame0, frame1, xy = _jump_frames()
    reference = ReferenceMatcher(SSDMeasure(SSDSettings()), MeasuredFilterSettings(lk_fallback=lk_fallback), len(xy),
                                 9.21)
    index = np.arange(len(xy))
    reference.start(index, frame0, xy)
    return frame0, frame1, xy, reference, index, np.repeat(np.eye(2)[None], len(xy), 0)


def _match(lk_fallback: bool, retry: np.ndarray | None = None, predicted_step: np.ndarray = np.zeros(2)):
    """The points of :func:`_jump_frames` and their measurement on frame 1, predicted moved by ``predicted_step``."""
    frame0, frame1, xy, reference, index, s_pred = _started(lk_fallback)
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
    assert np.all(on.jump == 0)  # a fallback centre's match is not a re-acquisition's jump


def test_only_points_found_before_are_tried():
    xy, found = _match(True)
    retry = np.arange(len(xy)) % 2 == 0
    _, measured = _match(True, retry)
    np.testing.assert_array_equal(measured.valid[retry], found.valid[retry])
    assert not np.any(measured.valid[~retry] & (np.linalg.norm(measured.z[~retry] - (xy[~retry] + JUMP), axis=1) < 2.0))
    assert np.all(measured.shift[~retry] == 0)


def test_a_point_lost_for_frames_is_found_again_around_where_it_was_last_seen():
    """Re-acquisition (issue 45): the points, found on frame 0 and then lost (not found on the frames since, so not
    retried), are predicted where they were while the frame moved by JUMP (an occluder carried the prediction
    off, or the point moved under it). Lost for 3 frames they are searched for around where they were last found
    and found at their true position; just found (lost for 0 frames) or lost for longer than ``REACQUIRE_FRAMES``
    they are not."""
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    not_retried = np.zeros(len(xy), bool)
    found = {}
    for lost_for in (0, 3, REACQUIRE_FRAMES + 1):
        found[lost_for] = reference.measure_in_gate(index, frame1, xy, s_pred, frame0, xy, not_retried,
                                                    np.full(len(xy), lost_for))
        on_truth = np.linalg.norm(found[lost_for].z - (xy + JUMP), axis=1) < 0.25
        assert np.array_equal(found[lost_for].valid & on_truth, found[lost_for].valid)  # never elsewhere
    assert found[3].valid.mean() >= 0.8
    np.testing.assert_allclose(found[3].shift[found[3].valid], np.broadcast_to(JUMP, xy.shape)[found[3].valid],
                               atol=2.0)  # the coarse search's centre, to its 2 px
    # the jump the error model reads (J): the match minus the prediction, on the points found again only
    np.testing.assert_array_equal(found[3].jump[found[3].valid], (found[3].z - xy)[found[3].valid])
    assert np.all(found[3].jump[~found[3].valid] == 0)
    assert not found[0].valid.any() and not found[REACQUIRE_FRAMES + 1].valid.any()


def test_a_lost_point_whose_last_patch_is_the_occluders_is_found_again_by_its_first_patch():
    """Re-acquisition by the first patch (issue 45): the points were dragged onto an occluder before they were lost,
    so their reference and last patch are the occluder's (here patches of noise, which match nothing of frame 1).
    Lost for 3 frames, they are found by their first patch at their true position, and take it back as their
    reference; with the last patch only (the first patch replaced by the occluder's too) none is found."""
    rng = np.random.default_rng(1)
    for with_first_patch in (True, False):
        frame0, frame1, xy, reference, index, s_pred = _started()
        occluder = _on_an_occluder(reference, index, frame0, xy, s_pred, rng)
        if not with_first_patch:
            reference.anchors[:] = occluder
            reference.anchor_half[:] = reference.last_patch
        found = _lost_for_three_frames(reference, index, frame0, frame1, xy, s_pred, with_first_patch)
        if with_first_patch:
            assert np.array_equal(reference.templates[~found.valid], occluder[~found.valid])


def _on_an_occluder(reference: ReferenceMatcher, index: np.ndarray, frame0: Frame, xy: np.ndarray,
                    s_pred: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Give the points of :func:`_started` their usual residual (matched on frame 0), then a reference and a last patch
    of noise, as an occluder that dragged them before they were lost leaves them; returns the (n, t, t) reference."""
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    occluder = rng.normal(128, 40, reference.templates.shape).astype(np.float32)
    reference._take(index, occluder, np.pad(occluder, [(0, 0)] + [(occluder.shape[1] // 2,) * 2] * 2, mode="edge"))
    reference.last_patch[:] = rng.normal(128, 40, reference.last_patch.shape)
    return occluder


def _lost_for_three_frames(reference: ReferenceMatcher, index: np.ndarray, frame0: Frame, frame1: Frame,
                           xy: np.ndarray, s_pred: np.ndarray, first_patch_finds: bool) -> GatedMeasurement:
    """The measurement on frame 1 of the points of :func:`_started`, lost for 3 frames and predicted where they were,
    checked: with ``first_patch_finds``, at least 80 % found at their true position, by their first patch, which they
    take back as their reference; else none found."""
    found = reference.measure_in_gate(index, frame1, xy, s_pred, frame0, xy, np.zeros(len(xy), bool),
                                      np.full(len(xy), 3))
    if not first_patch_finds:
        assert not found.valid.any()
        return found
    assert found.valid.mean() >= 0.8
    np.testing.assert_allclose(found.z[found.valid], (xy + JUMP)[found.valid], atol=0.25)
    np.testing.assert_array_equal(reference.templates[found.valid], reference.anchors[found.valid])
    return found


def test_a_point_dragged_out_of_reach_is_searched_for_by_its_first_patch_where_that_patch_last_held():
    """Re-acquisition by the first patch, around where the point was last found with a reference its first patch
    vouched for (issue 45): the points were dragged by an occluder, under references re-taken there that their
    first patch did not confirm, to 70 px left and below their query before they were lost. Where they were last
    found then lies beyond the coarse search's reach (80 px) of where they are on frame 1; where they were last
    found with a vouched reference (here the query) does not. Lost for 3 frames, they are found there by their first
    patch, at their true position; with only the square around where they were last found, none is."""
    rng = np.random.default_rng(1)
    drag = np.array([-70.0, 70.0])
    assert np.abs(JUMP - drag).min() > 2 * COARSE_REACH  # the square's half-side at full resolution
    for around_the_query in (True, False):
        frame0, frame1, xy, reference, index, s_pred = _started()
        _on_an_occluder(reference, index, frame0, xy, s_pred, rng)
        reference.last_seen[:] = xy + drag
        reference.vouched[:] = False
        np.testing.assert_array_equal(reference.vouched_seen, xy)  # taken at the query
        if not around_the_query:  # where it was last found steadily moved with it too (the test below has it stay)
            reference.vouched_seen[:] = reference.steady_seen[:] = reference.last_seen
        found = _lost_for_three_frames(reference, index, frame0, frame1, xy, s_pred, around_the_query)
        assert reference.vouched[found.valid].all()  # the first patch taken back is vouched for


def test_a_point_dragged_under_a_vouched_reference_is_searched_for_where_it_was_last_found_steadily():
    """Re-acquisition by the first patch around where the point was last found on ``STEADY_FRAMES`` frames in a row
    with a vouched reference (issue 45, dudek_03: a hand sweeping over the face, on whose edge the point was found
    for a frame or two at a time, the drift check confirming a re-take there, so that where it was last found with
    a vouched reference moved with the hand too). Both where the points were last found and where they were last
    found vouched lie 70 px left and below their query, beyond the coarse search's reach of where they are on frame
    1; where they were last found steadily (here the query) does not. Lost for 3 frames, they are found there by
    their first patch, at their true position; with that centre moved as well, none is."""
    rng = np.random.default_rng(1)
    drag = np.array([-70.0, 70.0])
    for around_the_query in (True, False):
        frame0, frame1, xy, reference, index, s_pred = _started()
        _on_an_occluder(reference, index, frame0, xy, s_pred, rng)
        reference.last_seen[:] = reference.vouched_seen[:] = xy + drag
        np.testing.assert_array_equal(reference.steady_seen, xy)  # taken at the query
        if not around_the_query:
            reference.steady_seen[:] = reference.last_seen
        _lost_for_three_frames(reference, index, frame0, frame1, xy, s_pred, around_the_query)


def test_where_a_point_was_last_found_steadily_moves_after_steady_frames_found_in_a_row():
    """``steady_seen`` follows the point only once it has been found with a vouched reference on ``STEADY_FRAMES``
    frames in a row: found on fewer (a frame or two on an occluder's edge between losses) it stays."""
    frame0, frame1, xy, reference, index, s_pred = _started()
    measured = reference.measure_in_gate(index, frame0, xy, s_pred)
    assert measured.valid.all()
    for run in range(1, STEADY_FRAMES + 1):
        reference.refresh(index, frame0, xy, frame0, xy + run, np.ones(len(xy), bool), measured)
        expected = xy + run if run >= STEADY_FRAMES else xy
        np.testing.assert_array_equal(reference.steady_seen, expected)
    lost = dataclasses.replace(measured, valid=np.zeros(len(xy), bool))
    reference.refresh(index, frame0, xy, frame0, xy + 10, np.ones(len(xy), bool), lost)
    reference.refresh(index, frame0, xy, frame0, xy + 11, np.ones(len(xy), bool), measured)
    np.testing.assert_array_equal(reference.steady_seen, xy + STEADY_FRAMES)  # one frame found since the loss


def test_a_point_both_searches_find_is_found_by_its_last_patch():
    """The re-acquisition measures the last patch's and the first patch's matches together and uses them in turn:
    where both find the point, the last patch's match is used and the point keeps its reference (re-taken here on
    frame 1 at the truth) instead of taking its first patch back."""
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    retaken = reference.measure.templates(frame1.gray, xy + JUMP)
    reference._take(index, retaken, reference._wide_patches(frame1, xy + JUMP))
    n = len(xy)
    found = reference.measure_in_gate(index, frame1, xy, s_pred, frame0, xy, np.zeros(n, bool), np.full(n, 3))
    assert found.valid.mean() >= 0.8
    np.testing.assert_allclose(found.z[found.valid], (xy + JUMP)[found.valid], atol=0.25)
    np.testing.assert_array_equal(reference.templates, retaken)


def _match_one_attempt(reference, index, tried, centre, frame, predicted, s_pred, gate, valid, shown, shift,
                       anchor=False, reach=None):
    """The re-acquisition's match of points ``tried`` around ``centre`` alone (one ``_attempt``, its fit bound
    ``REACQUIRE_FIT``), identity R_used; returns and updates as ``_match_attempts``."""
    attempt = reference._attempt(index, tried, centre, frame, predicted, s_pred, gate, anchor)
    return reference._match_attempts(index, [attempt], frame, predicted, s_pred, gate,
                                     np.repeat(np.eye(2)[None], len(index), 0), valid, shown, shift, REACQUIRE_FIT,
                                     reach)


def test_a_first_patch_match_is_weighed_against_the_first_patch_where_the_gate_matched():
    """The first patch's match around the truth (frame 1 = frame 0 moved by JUMP) is used although the gate's match,
    made with a reference re-taken on an occluder, fits that reference perfectly (residual 0 at the points' frame 0
    positions): the first patch is compared with its own fit there, which is poor, not with the reference's. Matched
    with the reference (a point whose reference is its first patch), the same match loses to that residual 0."""
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    n = len(xy)
    gate = Measurement(xy.copy(), np.repeat(np.eye(2)[None], n, 0), np.zeros(n), np.ones(n, bool), np.zeros(n))
    for anchor in (True, False):
        valid, shown, shift = np.zeros(n, bool), np.zeros(n, bool), np.zeros((n, 2))
        measured, _ = _match_one_attempt(reference, index, np.arange(n), xy + JUMP, frame1, xy, s_pred, gate, valid,
                                         shown, shift, anchor)
        if anchor:
            assert valid.mean() >= 0.8
            np.testing.assert_allclose(measured.z[valid], (xy + JUMP)[valid], atol=0.25)
        else:
            assert not valid.any()


def test_the_coarse_search_finds_a_half_resolution_patch_within_its_reach():
    """``coarse_search``: each point's patch of frame 0 at half resolution is found on frame 1 (moved by JUMP) to
    within 2 px of the full frame, from where it was on frame 0."""
    frame0, frame1, xy = _jump_frames()
    half0, half1 = HalfFrame(cv2.pyrDown(frame0.image)), HalfFrame(cv2.pyrDown(frame1.image))
    patches = extract_templates(half0.gray, xy / 2, COARSE_SIDE)
    np.testing.assert_allclose(coarse_search(patches, half1, xy), xy + JUMP, atol=2.0)


def _counted_searches(monkeypatch) -> list[int]:
    """The number of points of each ``coarse_search`` call from now on (the list grows as they are made)."""
    import condtrack_cli.filters.reference as module

    searched_for: list[int] = []
    search = module.coarse_search
    monkeypatch.setattr(module, "coarse_search",
                        lambda patches, cur, xy: searched_for.append(len(xy)) or search(patches, cur, xy))
    return searched_for


def test_a_lost_point_predicted_outside_the_frame_is_not_searched_for(monkeypatch):
    """Re-acquisition's skip: a lost point predicted outside the frame left it with the motion around it and is not
    searched for; the others are searched for and found as in the test above."""
    searched_for = _counted_searches(monkeypatch)
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    n = len(xy)
    outside = np.arange(n) < n // 3
    predicted = np.where(outside[:, None], [-5.0, 10.0], xy)
    found = reference.measure_in_gate(index, frame1, predicted, s_pred, frame0, xy, np.zeros(n, bool),
                                      np.full(n, 3))
    assert searched_for and searched_for[0] == 2 * (n - outside.sum())  # by their last and their first patch
    assert not found.valid[outside].any()
    assert found.valid[~outside].mean() >= 0.8
    np.testing.assert_allclose(found.z[found.valid], (xy + JUMP)[found.valid], atol=0.25)


def test_a_lost_point_never_matched_is_not_searched_for(monkeypatch):
    """Re-acquisition's skip: a lost point with no usual residual (never matched since its query) is not searched
    for, and could not have been found: even centred on its true position, its match fails the ``REACQUIRE_FIT``
    bound. The others are searched for and found as in the tests above."""
    searched_for = _counted_searches(monkeypatch)
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    n = len(xy)
    never = np.arange(n) % 3 == 0
    reference.usual[never] = np.nan
    found = reference.measure_in_gate(index, frame1, xy, s_pred, frame0, xy, np.zeros(n, bool), np.full(n, 3))
    assert searched_for and searched_for[0] == 2 * (n - never.sum())  # by their last and their first patch
    assert not found.valid[never].any()
    assert found.valid[~never].mean() >= 0.8
    gate = Measurement(xy.copy(), np.repeat(np.eye(2)[None], n, 0), np.full(n, np.nan), np.zeros(n, bool),
                       np.full(n, np.nan))
    valid, shown, shift = np.zeros(n, bool), np.zeros(n, bool), np.zeros((n, 2))
    _match_one_attempt(reference, index, np.flatnonzero(never), (xy + JUMP)[never], frame1, xy, s_pred, gate, valid,
                       shown, shift, reach=REACQUIRE_REACH)
    assert not valid.any()
    reference.usual[never] = 1e9  # the same matches with a yardstick: found
    _match_one_attempt(reference, index, np.flatnonzero(never), (xy + JUMP)[never], frame1, xy, s_pred, gate, valid,
                       shown, shift, reach=REACQUIRE_REACH)
    assert valid[never].mean() >= 0.8


def test_a_lost_point_whose_reference_is_about_as_flat_as_the_noise_is_not_searched_for(monkeypatch):
    """Re-acquisition's skip (``REACQUIRE_TEXTURE``): a lost point whose reference's texture (its cost against a flat
    patch) is at most ``REACQUIRE_TEXTURE`` times the noise's m 2 sigma^2 is not searched for; one just above the
    bound, and the textured points, are searched for and found as in the tests above. The photograph's corners are
    far above the bound (a flat patch is not a corner)."""
    searched_for = _counted_searches(monkeypatch)
    frame0, frame1, xy, reference, index, s_pred = _started()
    assert reference.measure_in_gate(index, frame0, xy, s_pred).valid.all()  # each point's usual residual
    n = len(xy)
    bound = REACQUIRE_TEXTURE * reference._noise_ssd()
    assert (reference.flat_cost > 10 * bound).all()
    flat, above = np.arange(n) % 3 == 0, np.arange(n) % 3 == 1
    reference.flat_cost[flat] = bound
    reference.flat_cost[above] = np.nextafter(bound, np.inf)
    found = reference.measure_in_gate(index, frame1, xy, s_pred, frame0, xy, np.zeros(n, bool), np.full(n, 3))
    assert searched_for == [2 * (n - flat.sum())]  # by their last and their first patch
    assert not found.valid[flat].any()
    assert found.valid[~flat].mean() >= 0.8 and found.valid[above].mean() >= 0.8


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


def test_where_lucas_kanade_fails_the_last_measured_step_is_the_next_centre(monkeypatch):
    """With Lucas-Kanade failing everywhere (its status false, as where an object's edge fills its window) and the
    coarse search finding nothing new (its centres the previous positions, inside the gate searched), a point
    whose last measured step is JUMP is found around x_prev + JUMP, the prediction moved there; a point with no
    measured step (NaN: not found on two frames running) is not found."""
    from condtrack_cli.filters import reference as module

    monkeypatch.setattr(module, "lk_centres", lambda prev, cur, xy: (xy, np.zeros(len(xy), bool)))
    monkeypatch.setattr(module, "coarse_centres", lambda prev, cur, xy: xy)
    frame0, frame1, xy = _jump_frames()
    measure = SSDMeasure(SSDSettings())
    matcher = ReferenceMatcher(measure, MeasuredFilterSettings(), len(xy), 9.21)
    index = np.arange(len(xy))
    matcher.start(index, frame0, xy)
    stepped = index % 2 == 0
    matcher.step[stepped] = JUMP
    measured = matcher.measure_in_gate(index, frame1, xy, np.repeat(np.eye(2)[None], len(xy), 0), frame0, xy,
                                       np.ones(len(xy), bool))
    xy, oracle = _match(False, predicted_step=JUMP)
    np.testing.assert_array_equal(measured.valid[stepped], oracle.valid[stepped])
    np.testing.assert_allclose(measured.z[measured.valid], (xy + JUMP)[measured.valid], atol=0.25)
    np.testing.assert_array_equal(measured.shift[measured.valid], np.broadcast_to(JUMP, xy.shape)[measured.valid])
    assert not np.any(measured.valid[~stepped] & (np.linalg.norm(measured.z[~stepped] - (xy + JUMP)[~stepped],
                                                                  axis=1) < 2.0))


def test_the_reference_records_the_step_of_points_found_on_both_frames():
    """``refresh`` keeps x_post - x_prev as the step of the points found before and now, NaN for the others."""
    frame0, frame1, xy = _jump_frames()
    _, measured = _match(True)
    matcher = ReferenceMatcher(SSDMeasure(SSDSettings()), MeasuredFilterSettings(), len(xy), 9.21)
    index = np.arange(len(xy))
    matcher.start(index, frame0, xy)
    found_before = index % 3 != 0
    matcher.refresh(index, frame0, xy, frame1, xy + JUMP, found_before, measured)
    both = found_before & measured.valid
    assert both.sum() >= 5
    np.testing.assert_array_equal(matcher.step[both], np.broadcast_to(JUMP, xy.shape)[both])
    assert np.isnan(matcher.step[~both]).all()


def test_the_coarse_search_finds_a_jump_with_no_prediction():
    """``coarse_centres``: the points of frame 0 are found on frame 1 (moved by JUMP) to within 2 px (the search's
    grid is 2 px of the full frame), with no prediction, and so are they where the jump is 70 px (within the
    80 px search)."""
    frame0, frame1, xy = _jump_frames()
    centre = coarse_centres(HalfFrame(cv2.pyrDown(frame0.image)), HalfFrame(cv2.pyrDown(frame1.image)), xy)
    np.testing.assert_allclose(centre, xy + JUMP, atol=2.0)
    photo = load_asset("camera.png")
    far = np.array([70.0, 0.0])
    before, after = photo[100:300, 150:450], photo[100:300, 80:380]  # the content moves 70 px right
    points = cv2.goodFeaturesToTrack(before, 30, 0.02, 12)[:, 0].astype(np.float64)
    points = points[(points[:, 0] >= 20) & (points[:, 0] + far[0] <= 279) & (points[:, 1] >= 20) & (points[:, 1] <= 179)]
    assert len(points) >= 5
    found = coarse_centres(HalfFrame(cv2.pyrDown(before)), HalfFrame(cv2.pyrDown(after)), points)
    np.testing.assert_allclose(found, points + far, atol=2.0)


def test_where_no_other_centre_finds_a_point_the_coarse_search_does(monkeypatch):
    """With Lucas-Kanade failing everywhere and no measured step, the points found on frame 0 are found on frame 1
    (moved by JUMP) around the coarse search's centre, as where the prediction is right."""
    from condtrack_cli.filters import reference as module

    monkeypatch.setattr(module, "lk_centres", lambda prev, cur, xy: (xy, np.zeros(len(xy), bool)))
    xy, measured = _match(True)
    xy, oracle = _match(False, predicted_step=JUMP)
    np.testing.assert_array_equal(measured.valid, oracle.valid)
    np.testing.assert_allclose(measured.z[measured.valid], (xy + JUMP)[measured.valid], atol=0.25)
