"""The reference patch warped by the local field's deformation (``warp_reference``, ``filters/reference.py``; issue 45).

Known truth: frame 1 is frame 0 (a photograph, with noise) zoomed by ``ZOOM`` about the crop's centre, as a driving
camera's scene grows; a point p of frame 0 is at c + ZOOM (p - c) on frame 1. The filters' local field would give
A_k = ZOOM I there; the tests pass it to the reference themselves.
"""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.filters.reference import GatedMeasurement, ReferenceMatcher
from condtrack_cli.filters.settings import MeasuredFilterSettings
from condtrack_cli.measure.response import SSDSettings
from condtrack_cli.measure.ssd import SSDMeasure
from condtrack_cli.types import Frame

from conftest import load_asset

ZOOM = 1.15


def _zoomed_frames() -> tuple[Frame, Frame, np.ndarray, np.ndarray]:
    """Frames 0 and 1 (frame 1 = frame 0 zoomed by ZOOM about the centre), (n, 2) textured points of frame 0 and
    (n, 2) their true positions on frame 1."""
    rng = np.random.default_rng(0)
    photo = load_asset("camera.png").astype(np.float32)
    crop = photo[40:280, 40:320]
    h, w = crop.shape
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    zoom = np.array([[ZOOM, 0.0, (1 - ZOOM) * centre[0]], [0.0, ZOOM, (1 - ZOOM) * centre[1]]])
    moved = cv2.warpAffine(crop, zoom, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    images = [np.clip(c + rng.normal(0, 1.0, c.shape), 0, 255).astype(np.uint8) for c in (crop, moved)]
    corners = cv2.goodFeaturesToTrack(images[0], 60, 0.02, 12)[:, 0].astype(np.float64)
    truth = centre + ZOOM * (corners - centre)
    inside = (corners >= 30).all(axis=1) & (corners <= [w - 31, h - 31]).all(axis=1)
    inside &= (truth >= 30).all(axis=1) & (truth <= [w - 31, h - 31]).all(axis=1)
    return Frame(0, images[0]), Frame(1, images[1]), corners[inside], truth[inside]


def _measured(warp_reference: bool, deformation: np.ndarray | None):
    """The points' truth on frame 1 and their measurement there, predicted 0.25 px off the truth, after the reference
    was told the step's (2, 2) linear map ``deformation`` (None: not told)."""
    frame0, frame1, xy, truth = _zoomed_frames()
    settings = MeasuredFilterSettings(warp_reference=warp_reference, lk_fallback=False)
    reference = ReferenceMatcher(SSDMeasure(SSDSettings()), settings, len(xy), 9.21)
    index = np.arange(len(xy))
    reference.start(index, frame0, xy)
    if deformation is not None:
        reference.deform(index, np.repeat(np.asarray(deformation)[None], len(xy), 0))
    predicted = truth + [0.2, -0.15]
    return truth, reference.measure_in_gate(index, frame1, predicted, np.repeat(np.eye(2)[None], len(xy), 0))


def test_a_warped_reference_is_matched_closer_to_the_truth_of_a_zoomed_scene():
    # Measured: median error 0.19 px as taken, 0.04 px warped; median residual halved.
    truth, plain = _measured(False, ZOOM * np.eye(2))
    _, warped = _measured(True, ZOOM * np.eye(2))
    assert len(truth) >= 15
    both = plain.valid & warped.valid
    assert both.sum() >= 10
    plain_error = np.linalg.norm(plain.z - truth, axis=1)[both]
    warped_error = np.linalg.norm(warped.z - truth, axis=1)[both]
    assert np.median(warped_error) < 0.5 * np.median(plain_error)
    assert np.median(warped_error) < 0.2
    assert np.median(warped.residual[both]) < 0.6 * np.median(plain.residual[both])


def test_a_warp_that_fits_worse_or_moves_the_patch_less_than_half_a_pixel_is_not_used():
    # The reference told of a 30 degree turn while the scene grew: the warped patch fits worse at the prediction,
    # and each point keeps its patch as taken: the measurement is the one without the warp, bit for bit.
    _, plain = _measured(False, None)
    turn = np.deg2rad(30.0)
    _, wrong = _measured(True, np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]))
    np.testing.assert_array_equal(wrong.z, plain.z)
    np.testing.assert_array_equal(wrong.residual, plain.residual)
    _, untold = _measured(True, None)  # no deformation told: J is the identity, nothing is warped
    np.testing.assert_array_equal(untold.z, plain.z)
    _, slight = _measured(True, 1.05 * np.eye(2))  # moves no pixel of the 11 px patch by half a pixel: not warped
    np.testing.assert_array_equal(slight.z, plain.z)


def test_a_retaken_reference_starts_its_warp_again():
    frame0, frame1, xy, truth = _zoomed_frames()
    reference = ReferenceMatcher(SSDMeasure(SSDSettings()), MeasuredFilterSettings(), len(xy), 9.21)
    index = np.arange(len(xy))
    reference.start(index, frame0, xy)
    reference.deform(index, np.repeat(ZOOM * np.eye(2)[None], len(xy), 0))
    np.testing.assert_allclose(reference.warp, ZOOM * np.eye(2)[None].repeat(len(xy), 0))
    reference.start(index[:3], frame1, truth[:3])
    np.testing.assert_array_equal(reference.warp[:3], np.eye(2)[None].repeat(3, 0))
    np.testing.assert_allclose(reference.warp[3:], ZOOM * np.eye(2)[None].repeat(len(xy) - 3, 0))


def test_a_warp_beyond_the_wide_patch_is_not_applied():
    # A textured 11 px square on flat grey, then a flat grey frame: a warp to a third of the size (J^-1 = 3.3) would
    # sample mostly the grey around the square, beyond the wide patch's 5 px margin, and fit the grey frame far
    # better than the square as taken; it is not represented by the wide patch, so the patch is matched as taken.
    rng = np.random.default_rng(1)
    image = np.full((80, 80), 100.0)
    image[35:46, 35:46] = rng.uniform(0, 255, (11, 11))
    frame0 = Frame(0, image.astype(np.uint8))
    frame1 = Frame(1, np.full((80, 80), 100, np.uint8))
    xy = np.array([[40.0, 40.0]])
    for side in (0.3, 0.8):  # J^-1 3.3: a pixel moves 11.7 px, beyond the 5 px margin; 1.25: 1.25 px, within it
        reference = ReferenceMatcher(SSDMeasure(SSDSettings()), MeasuredFilterSettings(), 1, 9.21)
        reference.start(np.arange(1), frame0, xy)
        reference.deform(np.arange(1), side * np.eye(2)[None])
        chosen = reference._references(np.arange(1), frame1, xy)
        assert np.array_equal(chosen, reference.templates[:1]) == (side == 0.3)


def _first_patch_matches(warp_reference: bool, lost: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the drift check finds each point's first patch on the zoomed frame 1 around estimates 0.4 px off the
    truth, whether it was found there, and the truth; the reference told of the zoom, and (``lost``) of a frame on
    which no point was found."""
    frame0, frame1, xy, truth = _zoomed_frames()
    n = len(xy)
    settings = MeasuredFilterSettings(warp_reference=warp_reference, lk_fallback=False)
    reference = ReferenceMatcher(SSDMeasure(SSDSettings()), settings, n, 9.21)
    index = np.arange(n)
    reference.start(index, frame0, xy)
    reference.deform(index, np.repeat(ZOOM * np.eye(2)[None], n, 0))
    if lost:
        unfound = GatedMeasurement(z=np.full((n, 2), np.nan), R=np.full((n, 2, 2), np.inf),
                                   R_used=np.full((n, 2, 2), np.inf), valid=np.zeros(n, bool),
                                   residual=np.full(n, np.nan), shown=np.zeros(n, bool), shift=np.zeros((n, 2)),
                                   jump=np.zeros((n, 2)))
        reference.refresh(index, frame0, xy, frame1, truth, np.zeros(n, bool), unfound)
    at, found = reference._anchored(index, frame1, truth + [0.25, -0.3])
    return at, found, truth


def test_the_drift_check_matches_the_first_patch_warped_while_the_point_has_been_found():
    # Measured: median error 0.04 px warped, 0.19 px as taken; every point found either way (at 0.6 px off the
    # truth 0.12 px warped: the warp is used only where it fits the frame at the estimate clearly better).
    at, found, truth = _first_patch_matches(True, lost=False)
    plain_at, plain_found, _ = _first_patch_matches(False, lost=False)
    assert found.sum() >= 10 and plain_found.sum() >= 10
    both = found & plain_found
    warped_error = np.linalg.norm(at - truth, axis=1)[both]
    plain_error = np.linalg.norm(plain_at - truth, axis=1)[both]
    assert np.median(warped_error) < 0.5 * np.median(plain_error)
    # a point not found since its query is matched with its first patch as taken: J ran through frames it missed
    lost_at, lost_found, _ = _first_patch_matches(True, lost=True)
    np.testing.assert_array_equal(lost_at, plain_at)
    np.testing.assert_array_equal(lost_found, plain_found)
