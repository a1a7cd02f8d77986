"""``auto``: each point to the filter its motion calls for (paper §5.3).

Rule, per point and per frame:
1. Trackability: a query point whose smaller structure-tensor eigenvalue is
   under the detector's floor (``detect.block``, ``detect.min_eigenvalue``) has
   no reliable local motion either; it stays with the CLF.
2. Motion-based segmentation (Irani, Rousso & Peleg 1994): the robust weights
   of the global fit mark the pixels that follow the dominant motion. A point's
   evidence w_k is the mean weight over the ``motion.local_window`` square
   around it, or 0 when its last measurement fell outside the gate that the
   dominant motion alone would give (``_check_dominant``: the point itself
   did not move with the dominant motion), or while it has not been found
   once since its query frame (its dynamics were wrong from the start; this
   also catches a point queried as it emerges from behind an occluder, whose
   backward pass loses it at once). Its support integrates the evidence
   over frames: s <- (1 - a) s + a w_k with a = 1 / ``integration_frames``
   (s = w on the first frame).
3. A point starts with the CLF; it moves to the CNLF when s falls below
   ``support_low`` and back to the CLF when s rises above ``support_high`` (a
   hysteresis, so that a point on the border does not flip every frame), and
   only while it is visible or not yet found since its query: an occluded
   point's neighbourhood is the occluder's, whose motion says nothing of the
   point's. The thresholds follow the dominant model's one-step prediction
   error on the real sequences of ../shared/data (``python -m
   condtrack_cli.evaluate.bench --support SEQUENCE``): median 0.45-1.1 px
   where the support is >= 0.8, 0.9-2.7 px in [0.6, 0.8), 2.3-5.4 px in
   [0.4, 0.6), about 10 px below 0.4 (kt3dmoseg_seq005_clip01, oxford_dinosaur). The
   state is handed over: particles drawn from N(x, Sigma) one way, the particle
   mean and covariance the other way.
The ``method`` of each row says which filter produced it.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from pydantic import Field, model_validator

from condtrack_cli.config import Config, StageSettings
from condtrack_cli.detect.shi_tomasi import trackable
from condtrack_cli.filters.base import Tracker
from condtrack_cli.filters.clf import CLFTracker, build_stage
from condtrack_cli.filters.cnlf import CNLFTracker
from condtrack_cli.filters.reference import ReferenceMatcher
from condtrack_cli.filters import kalman
from condtrack_cli.motion.robust import displacement, neighbourhood_support
from condtrack_cli.registry import method_code, register
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks


class AutoSettings(StageSettings):
    integration_frames: int = Field(3, ge=1, description="frames over which a point's support is averaged")
    support_low: float = Field(0.6, ge=0, le=1, description="to the CNLF when the support falls below this")
    support_high: float = Field(0.8, ge=0, le=1, description="back to the CLF when the support rises above this")

    @model_validator(mode="after")
    def _thresholds_in_order(self) -> "AutoSettings":
        if self.support_low > self.support_high:
            raise ValueError(f"'filter.auto.support_low' ({self.support_low:g}) must not exceed "
                             f"'filter.auto.support_high' ({self.support_high:g})")
        return self


class AutoTracker(Tracker):
    """Routes points between a CLF and a CNLF that share their reference patches."""

    method = "clf"

    def __init__(self, settings: AutoSettings, queries: Queries, info: SequenceInfo, config: Config,
                 rng: np.random.Generator):
        super().__init__(queries, info)
        self.settings = settings
        p = len(queries)
        reference = ReferenceMatcher(build_stage(config, "measure"), config.filters["clf"], p)
        self.clf = CLFTracker(config.filters["clf"], queries, info, config, reference)
        self.cnlf = CNLFTracker(config.filters["cnlf"], queries, info, config, rng, reference)
        self.window = config.stage("motion").settings.local_window
        self.detect = config.stage("detect").settings
        self.support = np.full(p, np.nan)
        self.on_cnlf = np.zeros(p, bool)
        self.trackable = np.ones(p, bool)
        self.follows = np.ones(p)  #: 1 while the point's measurements agree with the dominant motion, else 0
        self.measured = np.zeros(p, bool)  #: the point was found again at least once after its query frame
        self.q_floor = config.stage("motion").settings.q_floor
        self.gamma = self.clf.reference.measure.settings.gamma
        self.store_segmentation = config.output.store_segmentation
        self.segmentation: list[np.ndarray] = []  #: per frame pair, (H, W) uint8 255 x robust weight

    def step(self, frame: Frame, prev: Frame | None) -> FrameEstimate:
        self.cnlf.begin_frame()
        estimate = super().step(frame, prev)
        self.cnlf.end_frame()
        return estimate

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        self.trackable[index] = trackable(frame.gray, self.xy[index], self.detect.block, self.detect.min_eigenvalue)
        self.clf.xy[index], self.clf.visible[index] = self.xy[index], self.visible[index]
        self.clf._start(index, frame)
        self._collect(index, self.clf)

    def _route(self, index: np.ndarray, prev: Frame, frame: Frame) -> None:
        """Update the supports of points ``index`` and hand over those that change filter."""
        fit = self.clf.motion.fit(prev, frame)
        if self.store_segmentation:
            self.segmentation.append(np.rint(fit.weights * 255).astype(np.uint8))
        w = np.minimum(neighbourhood_support(fit, self.xy[index], self.window), self.follows[index])
        a = 1.0 / self.settings.integration_frames
        s = self.support[index]
        s = np.where(np.isnan(s), w, (1 - a) * s + a * w)
        self.support[index] = s
        seen = self.visible[index] | ~self.measured[index]  # an occluded point's neighbourhood is the occluder's
        to_cnlf = index[seen & ~self.on_cnlf[index] & self.trackable[index] & (s < self.settings.support_low)]
        to_clf = index[seen & self.on_cnlf[index] & (s > self.settings.support_high)]
        if to_cnlf.size:
            self.cnlf.adopt(to_cnlf, frame.index, self.xy[to_cnlf], self.cov[to_cnlf])
            self.cnlf.visible[to_cnlf] = self.visible[to_cnlf]
            self.on_cnlf[to_cnlf] = True
        if to_clf.size:
            self.clf.xy[to_clf], self.clf.cov[to_clf] = self.xy[to_clf], self.cov[to_clf]
            self.clf.visible[to_clf] = self.visible[to_clf]
            self.cnlf.release(to_clf)
            self.on_cnlf[to_clf] = False

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame) -> None:
        self._route(index, prev, frame)
        x_prev = self.xy[index].copy()
        for tracker, members in ((self.clf, index[~self.on_cnlf[index]]), (self.cnlf, index[self.on_cnlf[index]])):
            tracker.z[members], tracker.R[members] = np.nan, np.nan
            if members.size:
                tracker._advance(members, prev, frame)
            self._collect(members, tracker)
        self._check_dominant(index, x_prev, self.clf.motion.fit(prev, frame))

    def _check_dominant(self, index: np.ndarray, x_prev: np.ndarray, fit) -> None:
        """Did each measured point move as the dominant motion says? Sets ``follows`` to 1 or 0.

        A point follows when its measurement z_k falls in the gate that the
        dominant motion alone would give: nu = z_k - (x + U(x)), nu^T (q_floor I +
        R_k)^-1 nu <= gamma. Points without a measurement keep their value.
        """
        never_found = ~self.visible[index] & ~self.measured[index]  # not found once since its query frame
        self.follows[index[never_found]] = 0.0
        seen = self.visible[index]
        self.measured[index[seen]] = True
        if not seen.any():
            return
        x = x_prev[seen]
        nu = self.z[index[seen]] - (x + displacement(fit, x))
        spread = self.q_floor * np.eye(2) + self.R[index[seen]]
        self.follows[index[seen]] = (kalman.mahalanobis2(nu, spread) <= self.gamma).astype(float)

    def _collect(self, index: np.ndarray, tracker: Tracker) -> None:
        """Copy the state of points ``index`` from ``tracker`` into the router's report."""
        for name in ("xy", "cov", "visible", "z", "R"):
            getattr(self, name)[index] = getattr(tracker, name)[index]
        self.method_code[index] = method_code(tracker.method)

    def finish(self, history: list[FrameEstimate]) -> Tracks:
        """Tracks whose CNLF segments still open at the end carry the particle path means."""
        tracks = super().finish(history)
        extras = self.cnlf.extras()
        if self.store_segmentation and self.segmentation:
            extras["segmentation"] = np.stack(self.segmentation)
        return dataclasses.replace(tracks, xy=self.cnlf.path_means(tracks.xy), extras=extras)


@register("filter", "auto", AutoSettings, "each point to the CLF or the CNLF by motion segmentation (paper §5.3)")
def make_auto(settings: AutoSettings, queries: Queries, info: SequenceInfo, config: Config, rng: np.random.Generator,
              **_context) -> AutoTracker:
    return AutoTracker(settings, queries, info, config, rng)
