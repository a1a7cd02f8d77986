"""The trackability test of query points (paper §5.3; issue 29): each query's Shi-Tomasi score at its query frame.

The detector keeps only points whose score (the smaller eigenvalue of the
structure tensor over ``detect.block``, ``shi_tomasi.scores_at``) exceeds
``detect.min_eigenvalue``; user-given queries get the same score, computed on
their own query frames, and ``detect.untrackable`` (``--untrackable``, the API's
``untrackable=``) says what happens to those at or below the floor:

- ``keep`` (default): tracked like the others, with one warning giving the count;
- ``drop``: not tracked: they are absent from the outputs (the others keep their
  point ids), with the same warning;
- ``error``: the run stops before any tracking with a CondtrackError giving the count.

The scores are written to ``/tracks/trackability`` (docs/schema.md).
"""

from __future__ import annotations

import itertools
from typing import Iterable

import numpy as np

from condtrack_cli.detect.shi_tomasi import ShiTomasiSettings, scores_at
from condtrack_cli.errors import CondtrackError, warn
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Queries

#: The choices of ``detect.untrackable`` / ``--untrackable``.
POLICIES = ("keep", "drop", "error")


def trackability_settings(settings: StageSettings) -> tuple[int, float, str]:
    """(block, min_eigenvalue, untrackable) of the ``detect`` section; a detector without them gets Shi-Tomasi's defaults."""
    default = ShiTomasiSettings()
    return tuple(getattr(settings, key, getattr(default, key)) for key in ("block", "min_eigenvalue", "untrackable"))


def query_scores(frames: Iterable[np.ndarray], queries: Queries, block: int) -> np.ndarray:
    """(P,) float64 Shi-Tomasi score, (grey/px)^2, of each query at its query frame.

    ``frames`` iterates the sequence's (H, W) uint8 frames from frame 0; it is
    read up to the last query frame only, and each query frame's score map is
    computed once for all the points queried on it.
    """
    scores = np.full(len(queries), np.nan)
    if not len(queries):
        return scores
    wanted = set(np.unique(queries.frame).tolist())
    stream = iter(frames)
    try:
        for index, image in enumerate(itertools.islice(stream, int(queries.frame.max()) + 1)):
            if index in wanted:
                on = queries.frame == index
                scores[on] = scores_at(image.astype(np.float32), queries.xy[on], block)
    finally:
        if hasattr(stream, "close"):  # a video reader's generator releases its decoder now, not at collection
            stream.close()
    return scores


def _number(value: float) -> str:
    return np.format_float_positional(float(value), precision=3, trim="0")


def screen_queries(queries: Queries, scores: np.ndarray, floor: float, policy: str) -> tuple[Queries, np.ndarray]:
    """The queries (and their (P,) scores) to track under ``policy`` (module docstring).

    Warns (keep, drop) or raises (error, or drop when none is left) when any
    score is at or below ``floor``, naming the count and the first such point.
    """
    failing = ~(scores > floor)
    if not failing.any():
        return queries, scores
    first = int(np.argmax(failing))
    x, y = queries.xy[first]
    what = (f"{int(failing.sum())} of {len(queries)} queries are untrackable (Shi-Tomasi score below "
            f"detect.min_eigenvalue {_number(floor)}), e.g. point {int(queries.point_id[first])} at frame "
            f"{int(queries.frame[first])} ({_number(x)}, {_number(y)}), score {_number(scores[first])}")
    if policy == "error":
        raise CondtrackError(f"{what} (--untrackable error; keep tracks them anyway, drop leaves them out)")
    if policy == "keep":
        warn(f"{what}; tracked anyway (--untrackable keep)")
        return queries, scores
    if failing.all():
        raise CondtrackError(f"{what}: no query left to track (--untrackable drop)")
    warn(f"{what}; not tracked (--untrackable drop)")
    kept = ~failing
    return Queries(queries.point_id[kept], queries.frame[kept], queries.xy[kept]), scores[kept]
