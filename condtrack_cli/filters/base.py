"""The base class of every filter: the bookkeeping of the contract in ``interface.py``.

A tracker holds the state of all P points as arrays and advances the started
ones together, frame by frame: ``step`` first advances every point whose query
frame is before the current frame (``_advance``, one vectorised call on the
index array of those points, with the frame pair's motion that the pipeline
hands it), then starts the points queried on this frame (``_start``). It reports a :class:`FrameEstimate` for all P points each frame.
``finish`` turns the per-frame reports into :class:`Tracks`; a filter whose
estimate of past frames changes with later data (the particle filter's path
estimate) overrides it.
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.frame_reports import FIELDS, FrameReports
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.registry import method_code
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks


class Tracker:
    """Base of all filters; subclasses set ``method`` and implement ``_start``/``_advance``."""

    method: str = ""
    needs_motion: bool = False  #: :meth:`step` wants the global fit of each frame pair
    needs_local_motion: bool = False  #: :meth:`step` wants the local field of each frame pair too

    def __init__(self, queries: Queries, info: SequenceInfo):
        p = len(queries)
        self.queries = queries
        self.info = info
        self.xy = np.full((p, 2), np.nan)
        self.cov = np.full((p, 2, 2), np.nan)
        self.visible = np.zeros(p, bool)
        #: (P,) bool: not measured on this frame (R = inf, the surface too flat) but fitting its reference there:
        #: reported visible, while ``visible`` (the point was found) drives the filter (``reference.py``)
        self.seen_unmeasured = np.zeros(p, bool)
        self.z = np.full((p, 2), np.nan)
        self.R = np.full((p, 2, 2), np.nan)
        self.method_code = np.full(p, -1, np.int8)

    def step(self, frame: Frame, prev: Frame | None, motion: FrameMotion | None) -> FrameEstimate:
        """Advance the started points from ``prev`` to ``frame`` by ``motion``, start the new ones, report all."""
        self.z[:] = np.nan
        self.R[:] = np.nan
        self.seen_unmeasured[:] = False
        started = np.flatnonzero(self.queries.frame < frame.index)
        if prev is not None and started.size:
            self._advance(started, prev, frame, motion)
        new = np.flatnonzero(self.queries.frame == frame.index)
        if new.size:
            self.xy[new] = self.queries.xy[new]
            self.visible[new] = True
            self.method_code[new] = method_code(self.method)
            self._start(new, frame)
        return FrameEstimate(
            xy=self.xy.copy(), cov=self.reported_cov(), dof=self.reported_dof(),
            visible=self.visible | self.seen_unmeasured,
            z=self.z.copy(), R=self.R.copy(), method=self.method_code.copy(),
        )

    # What a router (``auto``) that splits the points between filters calls.

    def start_members(self, index: np.ndarray, frame: Frame, xy: np.ndarray) -> None:
        """Start points ``index`` at their queries xy (n, 2) px on ``frame``."""
        self.xy[index], self.visible[index] = xy, True
        self._start(index, frame)

    def take_over(self, index: np.ndarray, frame_index: int, xy: np.ndarray, cov: np.ndarray,
                  visible: np.ndarray) -> None:
        """Points ``index`` handed over from another filter at frame ``frame_index``: xy (n, 2) px, cov (n, 2, 2) px^2."""
        self.xy[index], self.cov[index], self.visible[index] = xy, cov, visible

    def advance_members(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion | None) -> None:
        """``_advance`` of points ``index`` alone (none: nothing), their z, R and ``seen_unmeasured`` reset first."""
        self.z[index], self.R[index], self.seen_unmeasured[index] = np.nan, np.nan, False
        if index.size:
            self._advance(index, prev, frame, motion)

    def reported_cov(self) -> np.ndarray:
        """(P, 2, 2) the covariance reported for the current frame: the filter's own unless overridden."""
        return self.cov.copy()

    def reported_dof(self) -> np.ndarray:
        """(P,) the Student-t degrees of freedom reported for the current frame: inf (Gaussian) unless overridden."""
        return np.where(np.isfinite(self.xy).all(axis=1), np.inf, np.nan)

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        """Initialise the filter state of points ``index`` (positions already set)."""

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion | None) -> None:
        """Move points ``index`` from ``prev`` to ``frame`` (``motion``: the pair's, as asked for); update xy, cov, visible, z, R."""
        raise NotImplementedError

    def smooth(self, tracks: Tracks) -> Tracks:
        """``tracks`` (from :meth:`finish`) with xy and cov smoothed over the whole pass (``filter.smooth``, taken only
        by a filter whose settings name their ``smoother``)."""
        raise NotImplementedError(f"{self.method} has no smoother")

    def finish(self, history: FrameReports) -> Tracks:
        """Stack the per-frame reports into (P, F, ...) arrays."""
        return Tracks(queries=self.queries, **{name: history.stack(name) for name in FIELDS})
