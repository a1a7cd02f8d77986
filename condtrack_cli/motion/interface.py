"""Contract of a ``motion`` stage: two consecutive frames in, their motion out (paper §5.1).

A motion stage is registered with ``register("motion", name, SettingsModel)`` on a
factory called ``factory(settings) -> MotionStages``. For a filter that needs
motion (``Tracker.needs_motion``) the pipeline calls, once per frame pair k-1 -> k
with a point started before k, the global estimator, then the local one on the
global fit when the filter needs it too (``Tracker.needs_local_motion``), and
hands the filter the result as a :class:`FrameMotion`. With more than one thread
it does so in a thread of its own, one pair ahead of the filter: a stage's
estimators are called from that thread alone, in pair order, and what they return
(read by the filter while they estimate the next pair) must not change afterwards
(work arrays reused from pair to pair stay inside the stage). A stage's
``field_source`` (``MotionStages``), when it has one, then computes each pair's
field in a third thread, a pair ahead of the estimators, and primes them with it. Positions are px of frame k-1 in the package's
pixel convention (x right, y down, (0, 0) the centre of the top-left pixel).
The built-in stages are rows of ``registry.BUILTINS`` instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from condtrack_cli.motion.model import MotionFit
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.types import Frame

if TYPE_CHECKING:
    from condtrack_cli.motion.field import LocalField


class GlobalMotionEstimator(Protocol):
    """The dominant motion of a frame pair."""

    def fit(self, prev: Frame, cur: Frame) -> MotionFit:
        """The parametric fit from ``prev`` (frame k-1) to ``cur`` (frame k): U(x) = P(x) theta, px."""


class LocalMotionEstimator(Protocol):
    """The motion of the window around every position (the CNLF's dynamics, eq. 5)."""

    def field(self, prev: Frame, cur: Frame, fit: MotionFit) -> LocalField:
        """The local field from ``prev`` to ``cur``, built on the global ``fit`` of the same pair.

        ``LocalField.displacement(xy)``: U(x) (..., 2) px; ``LocalField.noise(xy)``:
        Q_k(x) (..., 2, 2) px^2, at positions (..., 2) of frame k-1.
        """


class PairFieldSource(Protocol):
    """The part of a stage that reads the two frames' images alone (a dense field), which the pipeline may compute in
    a thread of its own, one pair ahead of the estimators (``pipeline.frame_motions``)."""

    def compute(self, prev: np.ndarray, cur: np.ndarray) -> np.ndarray:
        """The field from the (H, W) uint8 image ``prev`` (frame k-1) to ``cur`` (frame k); called from one thread
        alone, in pair order."""

    def prime(self, prev: Frame, cur: Frame, field: np.ndarray) -> None:
        """The estimators of ``prev`` and ``cur`` (called next, from the estimators' thread) use ``field``, the
        :meth:`compute` of their images."""


@dataclass(frozen=True)
class MotionStages:
    """What a motion factory builds: both estimators and Q_k of the global dynamics (eq. 1)."""

    global_motion: GlobalMotionEstimator
    local_motion: LocalMotionEstimator
    state_noise: StateNoise  #: Q_k (px^2) of the global fit's dynamics at any positions
    #: the estimators' shared field, which the pipeline computes a pair ahead of them with more than one thread
    #: (None: the estimators compute everything themselves)
    field_source: PairFieldSource | None = None


@dataclass(frozen=True)
class FrameMotion:
    """The motion of one frame pair k-1 -> k, as the pipeline hands it to ``Tracker.step``.

    global_fit: the dominant motion (``MotionFit``). local_field: the local field
    (``LocalField``), None when the filter does not need it.
    """

    global_fit: MotionFit
    local_field: LocalField | None = None
