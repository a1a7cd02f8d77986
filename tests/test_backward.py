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


@pytest.mark.parametrize("query_frame", [0, 3])
def test_an_input_that_stops_short_of_its_counted_frames_is_an_error_naming_both(query_frame):
    """A video counted at 30 frames when opened but decoded to 8 on the reading (a damaged file, one that changed
    while it was read) is an error naming both counts, before a backward pass or a written file; before, its 8-frame
    tracks were written under the 30-frame count (a file the readers refuse)."""
    from condtrack_cli.errors import CondtrackError

    source, _, truth = sample_inputs("occlusion")
    short = [image for _, image in zip(range(8), source)]
    seen = np.flatnonzero(truth.visible[:, query_frame])[:4]
    queries = Queries(truth.point_id[seen], np.full(seen.size, query_frame), truth.gt_xy[seen, query_frame])
    with pytest.raises(CondtrackError, match=r"30 frames when it was opened, but reading stopped after 8 "):
        pipeline.run(short, source.info, load_config(None, method="clf"), queries)
