"""CLF: the conditional linear filter (paper §3, §5, Fig. 1), and MDR, its dynamics alone.

Per frame, for all started points at once:
- model: the robust motion between frames k-1 and k gives A_k, b_k of eq. (1)
  (A_k the Jacobian of x + U(x), b_k = x + U(x) - A_k x) and Q_k (§5.1).
  ``dynamics: global`` (the paper's CLF, and MDR): U is the global robust fit,
  exact for the affine model and linearised for the quadratic one, Q_k
  ``state_noise``. ``dynamics: local``: U and Q_k are the local motion around
  the point (the motion stage's local field, the CNLF's eq. 5), A_k its
  Jacobian by central differences over one node spacing. ``dynamics:
  select`` (default; a departure, docs/departures.md): each point starts on
  the local motion; after each frame where it is found, it goes to the global
  motion unless the local prediction fell ``select_margin`` px closer to its
  measurement than the global one, and goes back to the local motion once the
  local prediction has been that much closer on ``select_frames`` found frames
  running; a point not found keeps its choice (``CLFTracker._choose``). One
  frame is not enough: a point about to be covered is often last measured with
  its patch half on the occluder, a step that the local motion (the
  occluder's, near its edge) predicts better; switched on it, the point would
  coast with the occluder (occlusion scene: clf 0.957 -> 0.983 <delta_avg with
  two frames, DIS motion stage). The global
  quadratic model cannot follow the parallax of a driving scene (its
  one-step prediction misses by a median 3-4 px on kt3dmoseg_seq028, where
  the weakly textured points, with an uninformative SSD surface, coast on
  it); the local motion alone drags a covered point along with its occluder;
- prediction: x_{k|k-1} = A_k x + b_k, Sigma_{k|k-1} = A_k Sigma A_k^T + Q_k;
  under occlusion (R = inf, issue 31) Q_k of the dominant motion reads the neighbourhood support (its misfit term,
  ``state_noise.py``) the point had on its last step found at both ends, its own layer's, not the support around it
  now, which is its occluder's: a background point covered by a card that the dominant fit rejects grew by
  q_misfit = 100 px^2 a frame, its gate spread to the 16 px cap, where it took a match on the card or found the
  surface ambiguous when the card had left (issue 31's card and occlusion scenes, tuning seeds, auto <delta_avg
  card 0.929 / 0.827 / 0.968 -> 0.940 / 0.837 / 0.970, occlusion 0.988 / 0.968 / 0.991 -> 0.990 / 0.961 /
  0.991; clf occlusion 0.981 / 0.946 / 0.993 -> 0.982 / 0.961 / 0.993). The gate of the first frame not found
  still uses the support around the point (it may have moved with its neighbourhood); once not found, its
  covariance is predicted again with its own; ``auto`` notes the support of its CNLF points (``note_support``);
- measurement: SSD match of the reference patch in the validation gate (§5.2),
  R_k from the correlation surface (eqs. 8-10);
- update where R_k is finite and z_k is in the gate nu^T (Sigma + R_k)^-1 nu <= gamma;
  elsewhere the point coasts on the dynamics and is reported not visible
  (the gate and the reference update: ``reference.py``).
With ``filter.smooth`` the CLF records A_k, x_{k|k-1}, Sigma_{k|k-1} per frame
and :meth:`CLFTracker.smooth` runs the RTS smoother over them (``smoother.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from condtrack_cli.filters import kalman
from condtrack_cli.filters.base import Tracker
from condtrack_cli.detect.trackability import Aperture
from condtrack_cli.filters.calibration import ErrorModel
from condtrack_cli.filters.reference import GatedMeasurement, ReferenceMatcher
from condtrack_cli.filters.settings import CLFSettings, MDRSettings
from condtrack_cli.filters.smoother import TransitionLog, error_excess, rts
from condtrack_cli.measure.interface import Measurer
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.motion.field import LocalField
from condtrack_cli.motion.model import displacement, jacobian
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.types import Frame, Queries, SequenceInfo, Tracks


def linear_dynamics(fit, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_k (n, 2, 2) and b_k (n, 2) of eq. (1) at positions xy (n, 2): x + U(x) = A_k x + b_k near xy."""
    A = jacobian(fit, xy)
    b = xy + displacement(fit, xy) - np.einsum("nij,nj->ni", A, xy)
    return A, b


def local_dynamics(field: LocalField, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A_k (n, 2, 2), b_k (n, 2) of eq. (1) and Q_k (n, 2, 2) from the local field at xy (n, 2).

    A_k = I + dU/dx by central differences over one node spacing of the field.
    """
    h = field.spacing
    steps = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    u = field.displacement(xy[:, None, :] + steps[None])  # (n, 4, 2)
    A = np.eye(2) + np.stack([(u[:, 0] - u[:, 1]) / (2 * h), (u[:, 2] - u[:, 3]) / (2 * h)], axis=2)
    b = xy + field.displacement(xy) - np.einsum("nij,nj->ni", A, xy)
    return A, b, field.noise(xy)


class MDRTracker(Tracker):
    """MDR: points moved by the robust motion alone, no measurement.

    ``dynamics: global`` (default): the dominant (global robust) motion, the CLF's
    dynamics; ``local``: the local motion around each point (the motion stage's local
    field, as ``CLFTracker`` with ``dynamics: local``), the CNLF's. The paper's MDR is
    "our dynamics" (§6), compared with the CLF on Corridor and with the CNLF on Caltra.
    The covariance is the dynamics' own, A Sigma A^T + Q accumulated; a point is
    visible while it is inside the frame (MDR has no occlusion evidence).
    """

    method = "mdr"
    needs_motion = True

    def __init__(self, settings: MDRSettings, queries: Queries, info: SequenceInfo, state_noise: StateNoise):
        """state_noise: Q_k of the global dynamics."""
        super().__init__(queries, info)
        self.settings = settings
        self.state_noise = state_noise
        self.needs_local_motion = settings.dynamics == "local"

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        self.cov[index] = self.settings.initial_std**2 * np.eye(2)

    def _predict(self, index: np.ndarray, motion: FrameMotion,
                 support: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """x_{k|k-1} (n, 2), Sigma_{k|k-1} (n, 2, 2) of points ``index`` by the global fit, and the A_k (n, 2, 2) used.

        support (n,): the neighbourhood support that Q_k reads (``StateNoise.at``; None: around each point).
        """
        fit = motion.global_fit
        x = self.xy[index]
        A, b = linear_dynamics(fit, x)
        return *kalman.predict(x, self.cov[index], A, b, self.state_noise.at(fit, x, support)), A

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion) -> None:
        if self.needs_local_motion:
            x = self.xy[index]
            A, b, Q = local_dynamics(motion.local_field, x)
            self.xy[index], self.cov[index] = kalman.predict(x, self.cov[index], A, b, Q)
        else:
            self.xy[index], self.cov[index], _ = self._predict(index, motion)
        self.visible[index] = self.info.contains(self.xy[index])


class CLFTracker(MDRTracker):
    """CLF: MDR's prediction corrected by the SSD measurement with R_k from the surface."""

    method = "clf"

    def __init__(self, settings: CLFSettings, queries: Queries, info: SequenceInfo, state_noise: StateNoise,
                 reference: ReferenceMatcher, errors: ErrorModel, smooth: bool):
        """reference: the points' reference patches and gate; errors: the reported covariance's model;
        smooth: record what :meth:`smooth` needs (``filter.smooth``)."""
        super().__init__(settings, queries, info, state_noise)
        self.reference, self.errors = reference, errors
        self.needs_local_motion = settings.dynamics != "global"
        self.on_local = np.full(len(queries), self.needs_local_motion)  #: (P,) predicted by the local motion
        self.local_wins = np.zeros(len(queries), np.int32)  #: (P,) consecutive found frames the local motion won
        #: (P,) the dominant fit's neighbourhood support around the point on its last step found at both ends, the
        #: support of its own layer that Q_k reads while it is not found (NaN before such a step; ``note_support``)
        self.own_support = np.full(len(queries), np.nan)
        self.covering = np.zeros(len(queries), bool)  #: (P,) the next step covers these points' patches (``cover``)
        shapes = dict(A=(2, 2), x_pred=(2,), sigma_pred=(2, 2), sigma_post=(2, 2), excess=(2, 2))
        self.transitions = TransitionLog(len(queries), **shapes) if smooth else None

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        super()._start(index, frame)
        self.on_local[index] = self.needs_local_motion
        self.local_wins[index] = 0
        self.reference.start(index, frame, self.xy[index])
        self.errors.start(index, self.cov[index], frame.gray, self.xy[index])

    def step(self, frame: Frame, prev: Frame | None, motion: FrameMotion | None):
        self.errors.begin_frame()
        return super().step(frame, prev, motion)

    def reported_cov(self) -> np.ndarray:
        """The error model's covariance (``calibration.py``), not the one the gate uses."""
        return self.errors.reported.copy()

    def reported_dof(self) -> np.ndarray:
        """The error model's Student-t degrees of freedom (``calibration.py``)."""
        return self.errors.dof

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion) -> None:
        x_prev, found_before = self.xy[index].copy(), self.visible[index].copy()
        fit = motion.global_fit
        support = self.state_noise.support(fit, x_prev)
        own = self.own_support[index]
        hidden = ~found_before & np.isfinite(own)
        support[hidden] = own[hidden]  # not found on the previous frame: its own layer's, not its covering layer's
        x_global, sigma_global, A_global = self._predict(index, motion, support)
        x_pred, sigma_pred, A = x_global, sigma_global, A_global
        if self.needs_local_motion:
            A_local, b_local, Q_local = local_dynamics(motion.local_field, x_prev)
            x_local, sigma_local = kalman.predict(x_prev, self.cov[index], A_local, b_local, Q_local)
            local = self.on_local[index]
            x_pred = np.where(local[:, None], x_local, x_global)
            sigma_pred = np.where(local[:, None, None], sigma_local, sigma_global)
            A = np.where(local[:, None, None], A_local, A_global)
        if self.reference.settings.warp_reference:  # the neighbourhood's deformation: the local field's, else the fit's
            self.reference.deform(index, A_local if self.needs_local_motion else A_global)
        measured = self.reference.measure_in_gate(index, frame, x_pred, sigma_pred, prev, x_prev,
                                                  found_before & ~self.covering[index], self.errors.coasted[index])
        x_pred = x_pred + measured.shift  # moved where the fallback centre's match is used (``lk_fallback``)
        if self.covering[index].any():  # a router's finding: the match lies on what covers the point
            measured = dataclasses.replace(measured, valid=measured.valid & ~self.covering[index],
                                           shown=measured.shown & ~self.covering[index])
            self.covering[index] = False
        # A point found on the previous frame and not on this one is covered (or lost): its dynamics' noise is its own
        # layer's (issue 31), not that of the neighbourhood now covering it; Q_k read there sized the gate only.
        covered = found_before & ~measured.valid & ~self.on_local[index] & np.isfinite(own)
        if covered.any():
            sigma_pred[covered] = self._predict(index[covered], motion, own[covered])[1]
        self.note_support(index[found_before & measured.valid], support[found_before & measured.valid])
        if self.settings.dynamics == "select":
            self._choose(index, measured, x_global, x_local)
        if self.transitions is not None:  # what the update below uses, for the RTS smoother
            self.transitions.record(frame.index, index, A=A, x_pred=x_pred, sigma_pred=sigma_pred)
        self.xy[index], self.cov[index] = kalman.update(x_pred, sigma_pred, measured.z, measured.R_used, measured.valid)
        if self.transitions is not None:  # the filtered covariance (the reported one is the error model's)
            self.transitions.record(frame.index, index, sigma_post=self.cov[index])
        self.visible[index], self.seen_unmeasured[index] = measured.valid, measured.seen_unmeasured
        self.z[index], self.R[index] = measured.z, measured.R
        retaken = self.reference.refresh(index, prev, x_prev, frame, self.xy[index], found_before, measured)
        disagreement = x_local - x_global if self.needs_local_motion else np.zeros_like(x_global)
        self.errors.update(index, x_pred, sigma_pred, measured.z, measured.R_used, measured.valid, self.xy[index],
                           self.cov[index], retaken, disagreement,
                           self.reference.offset_floor[index], measured.jump)
        if self.transitions is not None:
            self.transitions.record(frame.index, index, excess=self.errors.reported[index] - self.cov[index])

    def _choose(self, index: np.ndarray, measured: GatedMeasurement, x_global: np.ndarray, x_local: np.ndarray) -> None:
        """``select``: which motion predicts points ``index`` next frame, from this frame's miss of each.

        The local prediction x_local (n, 2) wins a frame where it fell at least
        ``select_margin`` px closer to the measurement than the global one x_global
        (n, 2). A point found this frame goes to the global motion when the local one
        did not win, and to the local motion once it has won ``select_frames`` found
        frames running; a point not found keeps its choice (an occluded point's window
        moves with the occluder, so it must not switch to it while covered).
        """
        miss_global = np.linalg.norm(measured.z - x_global, axis=1)
        miss_local = np.linalg.norm(measured.z - x_local, axis=1)
        closer = miss_global - miss_local >= self.settings.select_margin
        found = index[measured.valid]
        self.local_wins[found] = np.where(closer[measured.valid], self.local_wins[found] + 1, 0)
        self.on_local[found] &= closer[measured.valid]
        self.on_local[found] |= self.local_wins[found] >= self.settings.select_frames

    def cover(self, index: np.ndarray) -> None:
        """Points ``index`` are being covered on the next step (``auto``'s rule 5): their gate's match, on the
        occluder, is not used (R_k = inf), so they coast on their dynamics and are reported not visible."""
        self.covering[index] = True

    def note_support(self, index: np.ndarray, support: np.ndarray) -> None:
        """Points ``index`` were found at both ends of this frame pair, starting where the dominant fit's
        neighbourhood support was (n,) ``support``: the support of their own layer, kept for Q_k while not found."""
        self.own_support[index] = support

    def predict_by_dominant(self, index: np.ndarray) -> None:
        """Points ``index`` are predicted by the dominant motion until ``select`` finds the local one better."""
        self.on_local[index] = False
        self.local_wins[index] = 0

    def smooth(self, tracks: Tracks, members: np.ndarray | None = None) -> Tracks:
        """``tracks`` (this filter's :meth:`finish`) with the RTS-smoothed xy and cov of each point's segments.

        members (P, F) bool: the frames this filter produced (all when None); a
        transition k-1 -> k is smoothed over when both frames are members.
        """
        n_frames = tracks.xy.shape[1]
        x_pred = self.transitions.stacked("x_pred", n_frames)
        linked = np.isfinite(x_pred).all(axis=-1)
        if members is not None:
            linked[:, 1:] &= members[:, 1:] & members[:, :-1]
        sigma_post = self.transitions.stacked("sigma_post", n_frames)
        # where the filter recorded none (query frames, frames on another filter): the reported covariance; a query
        # row's smoothed value is not reported (``pipeline.query_rows_kept``)
        filtered = np.where(np.isfinite(sigma_post), sigma_post, tracks.cov)
        xy, cov = rts(tracks.xy, filtered, x_pred, self.transitions.stacked("sigma_pred", n_frames),
                      self.transitions.stacked("A", n_frames), linked)
        return dataclasses.replace(tracks, xy=xy, cov=cov + error_excess(self.transitions.stacked("excess", n_frames)))


def make_mdr(settings: MDRSettings, *, queries: Queries, info: SequenceInfo, state_noise: StateNoise,
             **_context) -> MDRTracker:
    return MDRTracker(settings, queries, info, state_noise)


def make_clf(settings: CLFSettings, *, queries: Queries, info: SequenceInfo, measure: Measurer, gamma: float,
             state_noise: StateNoise, smooth: bool, aperture: Aperture | None = None, **_context) -> CLFTracker:
    reference = ReferenceMatcher(measure, settings, len(queries), gamma)
    return CLFTracker(settings, queries, info, state_noise, reference, ErrorModel(len(queries), gamma, aperture), smooth)
