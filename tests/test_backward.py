"""Queries in the middle of a clip are tracked backward too: found on the earlier frames (issue: any-frame queries)."""

from __future__ import annotations

import numpy as np
import pytest

from condtrack_cli import pipeline
from condtrack_cli.config import load_config
from condtrack_cli.types import Queries

from conftest import sample_inputs


@pytest.mark.parametrize("sample, share", [("camera_motion", 0.97), ("occlusion", 0.95)])
def test_points_queried_mid_clip_are_found_on_earlier_frames(sample, share):
    """Measured with the default method: 100 % (camera_motion) and 98.4 % (occlusion) within 1 px."""
    source, _, truth = sample_inputs(sample)
    k = 15
    seen = truth.visible[:, k]
    queries = Queries(truth.point_id[seen], np.full(seen.sum(), k), truth.gt_xy[seen, k])
    tracks = pipeline.run(source, source.info, load_config(None), queries)
    assert np.isfinite(tracks.xy).all()  # a position on every frame of the clip
    error = np.linalg.norm(tracks.xy - truth.gt_xy[seen], axis=-1)[:, :k]
    earlier = truth.visible[seen][:, :k]
    assert (error[earlier] < 1.0).mean() >= share
