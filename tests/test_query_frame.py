"""On its own query frame a point is visible and at its query, for every method (issue 16 item 1)."""

from __future__ import annotations

import numpy as np
import pytest

from condtrack_cli import pipeline, registry
from condtrack_cli.config import load_config
from condtrack_cli.frames.readers import FrameSettings, open_frames
from condtrack_cli.types import Queries


@pytest.mark.parametrize("method", registry.names("filter"))
def test_query_frame_row_is_visible(shifted_folder, method):
    """Queries on frames 0 and 3 (forward start and backward start) of a 6-frame clip."""
    folder, _ = shifted_folder
    source = open_frames(FrameSettings(), folder)
    queries = Queries(np.arange(4), np.array([0, 0, 3, 3]),
                      np.array([[100.0, 80.0], [200.0, 150.0], [120.0, 60.0], [220.0, 170.0]]))
    tracks = pipeline.run(source, source.info, load_config(None, [], method), queries)
    rows = np.arange(len(queries)), queries.frame
    assert tracks.visible[rows].all()
    np.testing.assert_array_equal(tracks.xy[rows], queries.xy)  # the query itself, not a particle cloud's mean
