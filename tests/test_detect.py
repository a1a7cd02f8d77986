"""Detection: spacing and border respected; the trackability test rejects flat and edge, accepts corners."""

from __future__ import annotations

import numpy as np

from condtrack_cli.detect.shi_tomasi import ShiTomasiSettings, detect_points, trackable


def test_detected_points_respect_spacing_and_border(photo):
    settings = ShiTomasiSettings(max_points=200, min_distance=12.0, border=20)
    xy = detect_points(settings, photo.astype(np.float32))
    assert 50 <= len(xy) <= 200
    h, w = photo.shape
    assert (xy >= 20).all() and (xy[:, 0] <= w - 21).all() and (xy[:, 1] <= h - 21).all()
    distances = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy)) * 1e9
    assert distances.min() >= 12.0 - 1e-6


def test_trackability_flat_edge_corner():
    image = np.full((64, 64), 60.0, np.float32)
    image[32:, 32:] = 200.0  # a bright quadrant: a corner at (31.5, 31.5), edges along x=31.5 and y=31.5
    image += np.random.default_rng(0).normal(0, 1.0, image.shape).astype(np.float32)
    points = np.array([[10.0, 10.0], [31.5, 50.0], [50.0, 31.5], [32.0, 32.0]])  # flat, edge, edge, corner
    result = trackable(image, points, block=7, floor=ShiTomasiSettings().min_eigenvalue)
    np.testing.assert_array_equal(result, [False, False, False, True])
