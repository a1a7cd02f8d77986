"""Score a tracking result against ground truth: align by point_id, then the TAP-Vid metrics."""

from __future__ import annotations

from condtrack_cli.evaluate.groundtruth import Aligned, GroundTruth, align, check_queries
from condtrack_cli.evaluate.metrics import tapvid_metrics
from condtrack_cli.types import Tracks


def score_tracks(tracks: Tracks, truth: GroundTruth, query_mode: str = "first", *,
                 from_csv: bool = False) -> tuple[dict, Aligned]:
    """The metrics dict of ``tapvid_metrics`` and the aligned arrays it was computed on.

    CondtrackError when a point's query is not on its ground truth (``check_queries``; ``from_csv``: the tracks
    were read from a CSV, whose queries are the points' first rows, so any row on the truth will do).
    """
    data = align(tracks, truth)
    check_queries(tracks, truth, any_row=from_csv)
    result = tapvid_metrics(
        data.pred_xy, data.pred_visible, data.pred_cov, data.gt_xy, data.gt_visible, data.gt_known,
        data.query_frame, query_mode, data.pred_dof,
    )
    return result, data
