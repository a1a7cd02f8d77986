"""Contract of a ``filter`` stage (a tracking method): queries, frames and their motion in, an estimate per frame out.

A filter is registered with ``register("filter", name, SettingsModel)`` on a
factory the pipeline calls once per pass with the filter's own settings and
keyword arguments (:class:`FilterFactory`; a factory takes the ones it needs and
``**_context`` for the others). The pipeline then calls, for each frame k of the
pass, ``tracker.step(frame, prev, motion)`` with the motion of k-1 -> k that the
tracker asked for (``needs_motion``, ``needs_local_motion``), and at the end
``finish`` (and ``smooth`` with ``filter.smooth``). The built-in filters are rows of
``registry.BUILTINS`` instead.

Positions are px (x right, y down, (0, 0) the centre of the top-left pixel),
covariances px^2; P points, F frames of the pass.
:class:`condtrack_cli.filters.base.Tracker` implements the bookkeeping: a filter
subclasses it and writes ``_start`` and ``_advance``.
"""

from __future__ import annotations

from typing import Mapping, Protocol

import numpy as np

from condtrack_cli.detect.trackability import Aperture
from condtrack_cli.frame_reports import FrameReports
from condtrack_cli.measure.interface import Measurer
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks


class Tracker(Protocol):
    """A filter tracking P points through one pass."""

    method: str  #: the method whose code (``registry.method_code``) its rows carry; a router's rows carry its members' codes
    #: ``step`` wants the global fit of each frame pair; read once, when the tracker is built (the motion
    #: of a pair may be estimated before the filter steps the pair's first frame)
    needs_motion: bool
    needs_local_motion: bool  #: ``step`` wants the local field of each frame pair too; read once, as ``needs_motion``

    def step(self, frame: Frame, prev: Frame | None, motion: FrameMotion | None) -> FrameEstimate:
        """Advance the points started before ``frame`` from ``prev``, start those queried on ``frame``, report all P.

        ``prev`` is None on the pass's first frame. ``motion`` is the motion from
        ``prev`` to ``frame`` when ``needs_motion`` and a point was started before
        ``frame`` (its ``local_field`` only when ``needs_local_motion``), else None.
        """

    def finish(self, history: FrameReports) -> Tracks:
        """The pass's (P, F, ...) tracks from the F per-frame reports."""

    def smooth(self, tracks: Tracks) -> Tracks:
        """``tracks`` (from ``finish``) with xy and cov smoothed over the whole pass (``filter.smooth``; called only
        when the filter's settings model names its ``smoother``, ``StageSettings``)."""


class FilterFactory(Protocol):
    """``factory(settings, **context)``: the tracker of one pass; the context is every keyword below."""

    def __call__(
        self,
        settings: StageSettings,
        *,
        queries: Queries,
        info: SequenceInfo,
        rng: np.random.Generator,
        measure: Measurer,
        gamma: float,
        state_noise: StateNoise,
        smooth: bool,
        store_particles: bool,
        store_segmentation: bool,
        filter_settings: Mapping[str, StageSettings],
        aperture: Aperture,
    ) -> Tracker:
        """Build the tracker.

        queries: the P points (query frame and xy px of each). info: the sequence.
        rng: the pass's only source of random draws. measure: the configured
        measurement stage. gamma: the gate nu^T S^-1 nu <= gamma (``measure.gamma``).
        state_noise: Q_k of the global dynamics (``motion.q_floor``, ``q_misfit``,
        ``misfit_window``). smooth: ``filter.smooth`` (record what ``smooth`` needs).
        store_particles, store_segmentation: the ``output`` switches of the optional
        datasets (``Tracks.extras``). filter_settings: every registered filter's
        settings by name, for a router that builds other filters (``auto``).
        aperture: the trackability test's window and floor (``detect.block``, ``detect.min_eigenvalue``):
        a query that fails it is reported uncertain along its aperture (``filters/calibration.py``, D).
        """
