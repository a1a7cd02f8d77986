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

:class:`Aperture` gives a kept untrackable point's reported covariance its
uncertainty along the aperture from the query frame on (``filters/calibration.py``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from condtrack_cli.detect.shi_tomasi import ShiTomasiSettings, scores_at, structure_tensors_at
from condtrack_cli.errors import CondtrackError, warn
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Queries

#: The choices of ``detect.untrackable`` / ``--untrackable``.
POLICIES = ("keep", "drop", "error")

#: Most that :class:`Aperture` widens the query's variance along a direction: floor / eigenvalue is capped here
#: (a std of sqrt(100) = 10 times the query's, 5 px with filter.*.initial_std 0.5).
MAX_APERTURE_RATIO = 100.0


@dataclass(frozen=True)
class Aperture:
    """The trackability test's window and floor (``detect.block``, ``detect.min_eigenvalue``), handed to the filters."""

    block: int
    floor: float

    def offset(self, gray: np.ndarray, xy: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """(n, 2, 2) px^2: how far along the aperture the reference patches taken at (n, 2) ``xy`` on the (H, W)
        float32 frame ``gray`` may stand from the points, given the queries' covariance (n, 2, 2) ``sigma``.

        With T = sum_i lambda_i v_i v_i^T the structure tensor over ``block`` (Shi & Tomasi; lambda_i in
        (grey/px)^2), the offset is sum_i (min(floor / lambda_i, MAX_APERTURE_RATIO) - 1)+ (v_i^T sigma v_i) v_i v_i^T:
        zero along every direction where the patch passes the trackability test (every direction of a
        trackable point), and along one where it does not, the query's variance grown as 1 / lambda_i, the
        law of a match's variance in the window's texture (Lucas-Kanade: sigma^2 T^-1), so that
        sigma + offset is sigma (floor / lambda_i) there: both directions on a flat region, along the edge on an edge.
        """
        values, vectors = np.linalg.eigh(structure_tensors_at(gray, np.asarray(xy, np.float64), self.block))
        ratio = self.floor / np.maximum(values, self.floor / MAX_APERTURE_RATIO)  # (n, 2)
        along = np.einsum("nki,nkl,nli->ni", vectors, sigma, vectors)  # v_i^T sigma v_i
        grow = np.maximum(ratio - 1.0, 0.0) * along
        return np.einsum("nki,ni,nli->nkl", vectors, grow, vectors)


def trackability_settings(settings: StageSettings) -> tuple[int, float, str]:
    """(block, min_eigenvalue, untrackable) of the ``detect`` section; a detector without them gets Shi-Tomasi's defaults."""
    default = ShiTomasiSettings()
    return tuple(getattr(settings, key, getattr(default, key)) for key in ("block", "min_eigenvalue", "untrackable"))


class QueryScorer:
    """Each query's Shi-Tomasi score, (grey/px)^2, taken on its own query frame as a pass reaches it.

    ``scores`` is (P,) float64, NaN for the queries whose frame has not been seen.
    """

    def __init__(self, queries: Queries, block: int):
        self.queries = queries
        self.block = block
        self.scores = np.full(len(queries), np.nan)

    def see(self, index: int, gray: np.ndarray) -> None:
        """Score the queries of frame ``index`` (its (H, W) float32 grey levels ``gray``), all at once."""
        on = self.queries.frame == index
        if on.any():
            self.scores[on] = scores_at(gray, self.queries.xy[on], self.block)


def query_scores(frames: Iterable[np.ndarray], queries: Queries, block: int) -> np.ndarray:
    """(P,) float64 Shi-Tomasi score, (grey/px)^2, of each query at its query frame, before any tracking.

    ``frames`` iterates the sequence's (H, W) uint8 frames from frame 0; it is
    read up to the last query frame only. (A tracking pass scores its queries on
    the way, ``pipeline.run``: this up-front pass is for the policies that act
    before tracking, drop and error.)
    """
    scorer = QueryScorer(queries, block)
    if not len(queries):
        return scorer.scores
    stream = iter(frames)
    try:
        for index, image in enumerate(itertools.islice(stream, int(queries.frame.max()) + 1)):
            scorer.see(index, image.astype(np.float32))
    finally:
        if hasattr(stream, "close"):  # a video reader's generator releases its decoder now, not at collection
            stream.close()
    return scorer.scores


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
