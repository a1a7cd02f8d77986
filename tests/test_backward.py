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


def test_forward_only_keeps_the_forward_rows_and_leaves_the_earlier_frames_empty(tmp_path):
    """``output.backward: false`` (``--forward-only``, ``forward_only=True``): the rows from each query frame on are
    the two-way run's bit for bit (the same forward pass), the frames before it have no state, and the
    progress total counts the forward pass only."""
    import condtrack_cli as ct

    source, _, truth = sample_inputs("occlusion")
    seen = np.flatnonzero(truth.visible[:, 0] & truth.visible[:, 12])
    k = np.where(np.arange(len(seen)) % 2 == 0, 0, 12)  # half the points queried at frame 12
    rows = np.column_stack([k, truth.gt_xy[seen, k]])
    both = ct.track(source.info.input, rows, method="clf")
    done = []
    ahead = ct.track(source.info.input, rows, method="clf", forward_only=True, progress=lambda i, n: done.append(n))
    after = np.arange(both.xy.shape[1])[None, :] >= k[:, None]
    assert np.isfinite(both.xy).all()
    assert np.array_equal(ahead.xy[after], both.xy[after]) and np.array_equal(ahead.cov[after], both.cov[after])
    assert np.array_equal(ahead.visible[after], both.visible[after])
    assert np.isnan(ahead.xy[~after]).all() and not ahead.visible[~after].any()
    assert set(done) == {source.info.n_frames}
    assert ahead.config.output.backward is False and "backward: false" in ahead.attributes["config"]
    with pytest.raises(TypeError, match="forward_only"):
        ct.track(source.info.input, rows, method="stk", forward_only="yes")
