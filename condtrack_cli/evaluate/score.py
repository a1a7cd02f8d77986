"""Score a tracking result against ground truth: align by point_id, then the TAP-Vid metrics."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from condtrack_cli.errors import CondtrackError
from condtrack_cli.evaluate.groundtruth import Aligned, GroundTruth, align, check_queries
from condtrack_cli.evaluate.metrics import tapvid_metrics
from condtrack_cli.queries import read_queries
from condtrack_cli.types import SequenceInfo, Tracks

#: Largest distance (px) between an HDF5 file's stored query and the same point's in a queries file.
QUERY_AGREEMENT_PX = 1e-6


def score_tracks(tracks: Tracks, truth: GroundTruth, query_mode: str = "first", *,
                 from_csv: bool = False, queries: str | Path | None = None) -> tuple[dict, Aligned]:
    """The metrics dict of ``tapvid_metrics`` and the aligned arrays it was computed on.

    CondtrackError when a point's query is not on its ground truth (``check_queries``; ``from_csv``: the tracks
    were read from a CSV, whose queries are the points' first rows, so any row on the truth will do). ``queries``:
    the queries file the tracks were tracked from (``condtrack track -p``), giving each point its query
    (``with_queries``); a CSV's points are then scored from their query frames, as the HDF5 file of the same run.
    """
    if queries is not None:
        tracks = with_queries(tracks, queries, stored=not from_csv)
    data = align(tracks, truth)
    check_queries(tracks, truth, any_row=from_csv and queries is None)
    result = tapvid_metrics(
        data.pred_xy, data.pred_visible, data.pred_cov, data.gt_xy, data.gt_visible, data.gt_known,
        data.query_frame, query_mode, data.pred_dof,
    )
    return result, data


def with_queries(tracks: Tracks, path: str | Path, *, stored: bool) -> Tracks:
    """``tracks`` with each point's query frame and position from the queries CSV ``path``, matched by point_id.

    ``stored``: the tracks hold their own queries (HDF5), which must agree with the file's (same frame, position
    within ``QUERY_AGREEMENT_PX``). A point of the file absent from the tracks is ignored (``track --untrackable
    drop`` tracks only some of its points). CondtrackError naming ``path`` and the first point_id in the tracks but
    not in the file, or (``stored``) whose queries disagree.
    """
    given = read_queries(path, SequenceInfo(str(path), 0, 0, tracks.xy.shape[1], 0.0))  # the tracks' frames
    ids = np.asarray(tracks.queries.point_id, np.int64)
    absent = np.setdiff1d(ids, given.point_id)
    if len(absent):
        raise CondtrackError(f"{path}: point_id {absent[0]} is in the tracks but not in the queries file")
    index = np.searchsorted(given.point_id, ids)
    frame, xy = given.frame[index], given.xy[index]
    if stored:
        stored_xy = np.asarray(tracks.queries.xy, np.float64)
        wrong = (frame != tracks.queries.frame) | ~(np.hypot(*(xy - stored_xy).T) <= QUERY_AGREEMENT_PX)
        if wrong.any():
            i = int(np.argmax(wrong))
            raise CondtrackError(
                f"{path}: point_id {ids[i]}: the query, frame {frame[i]} ({xy[i, 0]:.10g}, {xy[i, 1]:.10g}), "
                f"disagrees with the tracks' own, frame {tracks.queries.frame[i]} "
                f"({stored_xy[i, 0]:.10g}, {stored_xy[i, 1]:.10g})"
            )
        return tracks
    return replace(tracks, queries=replace(tracks.queries, frame=frame, xy=xy))
