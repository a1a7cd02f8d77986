"""``auto``: each point to the filter whose dynamics its own measurements follow (paper §5.3, revised).

The paper routes by motion segmentation: points on the dominant motion's
support to the CLF, the others to the CNLF. Measured on the shared real sets,
the dominant motion's robust weights are a poor guide there (parallax on
driving video, a wide baseline on merton1: the fit's own MAD scale is 19-27
grey levels against noise 0.74), and a point the CLF has lost rarely comes
back; on the occlusion scene the CNLF sends a covered point with its occluder,
because a covered point's local motion is the occluder's. The rule keeps the
segmentation's idea (does this point move with the dominant motion or with its
own neighbourhood?) but asks the point's measurements instead of the weights.

Rule, per point, before each step:
1. A point starts on the CNLF: its local motion is the dominant one wherever
   the dominant one holds, and it follows parallax and independent objects
   where it does not.
2. Evidence: after each step with a measurement z_k in the gate, both
   dynamics predict z_k from the point's previous estimate x: dominant
   mu_d = A_k x + b_k (eq. 1), local mu_l = x + U_local(x) (eq. 5). In one
   common metric S = Sigma_{k-1} + R_k + q_floor I (so that neither model
   wins by a smaller Q alone: a calibrated Q is not what is being compared),
   e_k = (|z - mu_d|^2_S - |z - mu_l|^2_S) / 2 is > 0 where the local motion
   predicted better. The evidence averages it: E <- (1 - a) E + a e_k with
   a = 1 / ``integration_frames``.
3. Hysteresis: to the CLF when E < -``evidence_margin``, to the CNLF when
   E > ``evidence_margin``; in between the point stays where it is. A point on
   the CLF that the CLF already predicts by the local motion (its ``select``,
   ``clf.py``, chose it) stays on the CLF whatever E says (``keep_local_clf``;
   rule 4 still decides for a point not found): both filters would then follow
   the same motion, and the hand-over would only draw the CNLF's particles
   afresh around the CLF's estimate (docs/departures.md, "`auto` keeps a point
   on the CLF that follows the local motion").
4. While the point is not found (no measurement in the gate: covered, or
   lost), there is no measurement to weigh. It keeps the local motion when
   the mean of the e_k it has had (the same weights as E, normalised by their
   sum, so that one measurement counts fully) is above ``lost_evidence`` (0.25, half
   the margin; docs/departures.md, "`auto`'s lost-evidence threshold 0.25"): its
   measurements said the local motion predicts it better, and a point moving
   with its neighbourhood (parallax, an independent object) stays with it.
   Otherwise it asks which dynamics better continues its last measured step
   v: c = (|x + v - mu_d|^2_S - |x + v - mu_l|^2_S) / 2, with
   S = Sigma + (q_floor + r t^2 |v|^2 / 2) I. The extrapolation x + v is
   itself uncertain: t frames after v was measured, the step has changed by
   about t times one frame's change, and r, the relative change of a step
   (pooled E|v_k - v_{k-1}|^2 / E|v_{k-1}|^2 of the points found twice
   running), scales it with the point's speed, as parallax does (a static
   point's image speed grows in proportion to itself as the camera nears
   it). The point moves to the local motion when c > ``evidence_margin``, to
   the dominant one when c < -``evidence_margin``, and stays where it is in
   between (the hysteresis of rule 3). A covered point's neighbourhood jumps
   to the occluder's motion, away from v by the occluder's speed relative to
   the background, not by a share of the point's own speed, and before it was
   covered both motions predicted it alike (mean e_k near 0); so it coasts on
   the dominant motion (CLF) and is measured again around the right place.
   Rule 4 reads the evidence and the step v as they were before the point's
   last measurement (where it had an earlier one): a point about to be covered
   is often last measured with its patch half on the occluder, a step that moves
   with it and that the local motion predicts (occlusion scene, DIS motion
   stage: auto 0.935 -> 0.961 <delta_avg).
   A point handed to the CLF, or lost while on it, is predicted there by the
   dominant motion until the CLF's own ``select`` (``clf.py``) finds the
   local motion better again.
5. An occluder sweeping over a point still found (issue 31's card): a point on
   the CNLF, found on the previous frame, whose measurements did not favour
   the local motion (mean evidence, read as rule 4 reads it, at most
   ``lost_evidence``: a background point, both motions predicting it alike),
   and whose local step x + U_local(x) jumps away from its own measured step v
   (read as rule 4 reads it too: from before its last measurement, where it
   has an earlier one) by more than max(``occluder_jump``, |v|) px (``swept_by_occluder``, the test of the
   CNLF's ``layer_jump``, ``cnlf.departs``) while the dominant step continues it (within
   ``occluder_jump`` px: the point moved with the background) has an occluder's field around it:
   the point is handed to the CLF, predicted by the dominant motion for this
   step, and reported not visible whatever its gate found (its patch is being
   covered); rule 4 then keeps it on the dominant motion while it is not
   found. A jump of the camera moves both predictions and is not one.
   Measured on issue 31's tuning seeds 0-2 (``--hard tune``, auto <delta_avg
   off -> on, off = ``occluder_jump: null``): card 0.857 / 0.742 / 0.934 ->
   0.931 / 0.827 / 0.968 (OA 0.853 / 0.778 / 0.932 -> 0.898 / 0.837 / 0.965),
   occlusion 0.960 / 0.957 / 0.983 -> 0.975 / 0.954 / 0.990, jumps unchanged.
   Without the evidence condition the card gained less (0.903 / 0.826 /
   0.946: its own points, on the local motion, were swept too) and merton1
   lost 0.963 -> 0.870 (a wide baseline over 3 frames: a point's local step
   changes by more than its size from one frame to the next while a poor
   dominant fit happens to continue it). J = 1 and 4 px measured alike
   (without the evidence condition); reading v from before the last
   measurement did not help; letting the gate decide the visibility lost a
   little (card 0.896 / 0.822 / 0.946).
   ``occluder_jump`` 1.5 px (was 2, issue 31, with the DIS field's
   ``mean_normalization: select``): DIS blurs a moving bar's leading edge,
   so the local step at a background point about to be covered grows over
   two frames (occlusion seed 0, point 41: 1.3 -> 3.2 px while the bar moves
   8 px a frame, a departure of 1.7 px); at 2 px the point is not swept, the
   CNLF's gate, wide at the boundary, accepts a match on the bar, and the
   point rides it. Tuning seeds, auto <delta_avg 2 -> 1.5 px: occlusion
   0.967 / 0.961 / 0.991 -> 0.986 / 0.950 / 0.992, card 0.966 / 0.846 /
   0.991 -> 0.958 / 0.848 / 0.991, jumps unchanged; real sets unchanged
   (to 0.001).
   v from before the last measurement (issue 31, with the covered Q_k and the residual test below; it was the
   last measured step): a point whose last step was measured with its patch half on the bar has a step
   enlarged towards the bar's (occlusion seed 5, point 38: 1.62 -> 2.36 px while the background moves
   1.65 px), which raised the bound max(J, |v|) above the local step's departure (2.15 px) and the point rode
   the bar on the CNLF. Tuning seeds, auto <delta_avg / OA: occlusion 0.994 / 0.964, 0.992 / 0.961, 0.992 /
   0.968 -> 0.995 / 0.962, 0.988 / 0.961, 0.992 / 0.968; card 0.944 / 0.910, 0.847 / 0.851, 0.972 / 0.973 ->
   0.944 / 0.910, 0.845 / 0.859, 0.972 / 0.973; jumps 0.989 / 0.974 -> 0.991 / 0.972 (seed 0), the others
   equal; occlusion seeds 8-13, auto <delta_avg 0.987 / 0.981 / 0.970 / 0.985 / 0.998 / 0.951 -> 0.987 /
   0.981 / 0.970 / 0.986 / 0.996 / 0.956.
   The swept point's gate match, on the occluder, is not used (``CLFTracker.cover``): before, it was reported
   not visible but the CLF's update had moved it onto the occluder (issue 31's tuning seeds with the CLF's
   covered Q_k, auto <delta_avg / OA card 0.940 / 0.908, 0.837 / 0.849, 0.970 / 0.968 -> 0.940 / 0.908,
   0.847 / 0.857, 0.970 / 0.968; occlusion 0.990 / 0.961 / 0.991 -> 0.991 / 0.975 / 0.991).
The state is handed over: particles drawn from N(x, Sigma) one way, the
particle mean and covariance the other way. The ``method`` of each row says
which filter produced it. The rule does not assume which filter is the more
accurate: a better CLF wins more points through (2) and (3).

Measured with ``python -m condtrack_cli.evaluate.bench --versus-lk``
(<delta_avg, issue 11 protocol, seed 0; "first" = the
robust-weight rule of the first version, issue 11's table; auto / clf /
cnlf, with the robust motion stage of the time): kt3dmoseg seq005 0.728 /
0.730 / 0.723 (first 0.671), seq009 0.734 / 0.707 / 0.738 (0.523), seq011
0.914 / 0.907 / 0.913 (0.867), seq028 0.726 / 0.691 / 0.728 (0.434), seq059
0.778 / 0.752 / 0.779 (0.704), dinosaur 0.850 / 0.850 / 0.850 (0.774), merton1
0.771 / 0.763 / 0.771 (0.347); with the DIS stage: ``bench/results.md``.
Rule 4's evidence test: without it, points lost on parallax went to the
dominant motion, whose error grows by tens of pixels a frame there (seq009
auto 0.712 -> 0.740 and seq028 0.656 -> 0.687 when it came); its
extrapolation metric and hysteresis: seq009 0.726 -> 0.734, occlusion sample
0.974 -> 0.985 (docs/departures.md).
With ``filter.smooth`` each point's contiguous run of CLF frames is
RTS-smoothed and each run of CNLF frames FFBSm-smoothed (``smoother.py``); a
handover ends a run, so the frame before it keeps its filtered estimate.
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import numpy as np

from condtrack_cli.filters.base import Tracker
from condtrack_cli.detect.trackability import Aperture
from condtrack_cli.filters.calibration import ErrorModel
from condtrack_cli.filters.clf import CLFTracker, linear_dynamics
from condtrack_cli.filters.cnlf import CNLFTracker, departs, inverse2
from condtrack_cli.filters.reference import ReferenceMatcher
from condtrack_cli.filters.settings import AutoSettings, CLFSettings, CNLFSettings
from condtrack_cli.frame_reports import FrameReports
from condtrack_cli.measure.interface import Measurer
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.motion.state_noise import StateNoise
from condtrack_cli.registry import method_code
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks


def closer_to_local(z: np.ndarray, dominant: np.ndarray, local: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """(n,) (|z - dominant|^2_S - |z - local|^2_S) / 2 for (n, 2) points and (n, 2, 2) S: > 0 where local is closer."""
    inv = inverse2(spread)
    nu_d, nu_l = z - dominant, z - local
    return 0.5 * (np.einsum("ni,nij,nj->n", nu_d, inv, nu_d) - np.einsum("ni,nij,nj->n", nu_l, inv, nu_l))


def extrapolation_spread(cov: np.ndarray, velocity: np.ndarray, steps: np.ndarray, relative_change: float,
                         q_floor: float) -> np.ndarray:
    """(n, 2, 2) metric of rule 4 for (n, 2, 2) covariances, (n, 2) last measured steps v and (n,) frames since.

    cov + (q_floor + c t^2 |v|^2 / 2) I: the extrapolation x + v misses the next step by the change of
    the point's step over t frames, about t times one frame's (a steady acceleration, as on parallax,
    where a static point's image speed grows in proportion to itself); c = ``relative_change``, the
    pooled E|v_k - v_{k-1}|^2 / E|v_{k-1}|^2 of the points found twice running.
    """
    extrapolation = 0.5 * relative_change * np.square(steps) * np.einsum("ni,ni->n", velocity, velocity)
    return cov + (q_floor + extrapolation)[:, None, None] * np.eye(2)


def lost_on_local(
    x: np.ndarray, velocity: np.ndarray, spread: np.ndarray, dominant: np.ndarray, local: np.ndarray,
    mean_evidence: np.ndarray, lost_evidence: float, on_local: np.ndarray, margin: float,
) -> np.ndarray:
    """(n,) rule 4 for points not found: True where the point coasts on the local motion.

    x (n, 2) positions, velocity (n, 2) last measured steps (px/frame), spread
    (n, 2, 2) the metric, dominant and local (n, 2) the two predictions,
    mean_evidence (n,) the mean e_k of the point's measurements, on_local (n,)
    bool the dynamics the point follows now, kept while the extrapolation x + v
    is within ``margin`` (half squared Mahalanobis units) of telling them apart.
    """
    continued = closer_to_local(x + velocity, dominant, local, spread)
    return (mean_evidence > lost_evidence) | np.where(np.abs(continued) <= margin, on_local, continued > 0)


def swept_by_occluder(x: np.ndarray, velocity: np.ndarray, dominant: np.ndarray, local: np.ndarray,
                      jump: float) -> np.ndarray:
    """(n,) bool, rule 5: the local step jumps away from the point's last measured step v (``cnlf.departs``: by more
    than max(``jump`` px, |v|)) while the dominant step continues it (within ``jump`` px), as where an occluder sweeps
    over a background point.

    x (n, 2) positions, velocity (n, 2) last measured steps v (px/frame), dominant and local (n, 2) the one-step
    predictions of x by the two motions. A jump of the whole image (the camera's) moves both and is not one. The
    dominant step is held to ``jump`` px, not to max(``jump``, |v|): a point of an object entering at 40 px a frame
    over a still background (|v| = 40, a dominant step near 0) did not move with the background, and its local
    step, wrong where the field cannot follow the object, is no occluder's (issue 31's card scene).
    """
    return departs(local - x, velocity, jump) & (np.linalg.norm(dominant - x - velocity, axis=-1) <= jump)


class AutoTracker(Tracker):
    """Routes points between a CLF and a CNLF that share their reference patches."""

    method = "cnlf"
    needs_motion = True
    needs_local_motion = True

    def __init__(self, settings: AutoSettings, queries: Queries, info: SequenceInfo, clf: CLFTracker,
                 cnlf: CNLFTracker, errors: ErrorModel, q_floor: float, store_segmentation: bool):
        """clf, cnlf: the two filters, sharing their reference patches and ``errors``, the reported
        covariance's model; q_floor: the floor of Q_k (px^2, ``motion.q_floor``) in the common metric of
        rules 2 and 4; store_segmentation: :meth:`finish` returns the global fit's robust weights."""
        super().__init__(queries, info)
        self.settings = settings
        p = len(queries)
        self.errors, self.clf, self.cnlf, self.q_floor = errors, clf, cnlf, q_floor
        self.evidence = np.zeros(p)  #: averaged closer_to_local of the point's measurements
        self.evidence_weight = np.zeros(p)  #: sum of the averaging weights given so far (0 before a measurement)
        self.on_cnlf = np.zeros(p, bool)
        self.velocity = np.full((p, 2), np.nan)  #: px/frame, the point's last step that ended with a measurement
        #: evidence, its weight and velocity as they were before the point's last measurement (rule 4)
        self.before_last = (np.zeros(p), np.zeros(p), np.full((p, 2), np.nan))
        self._step_changes = np.zeros(2)  #: averaged sums of |v_k - v_{k-1}|^2 and of |v_{k-1}|^2 (px^2)
        self.store_segmentation = store_segmentation
        self.segmentation: list[np.ndarray] = []  #: per frame pair, (H, W) uint8 255 x robust weight

    def step(self, frame: Frame, prev: Frame | None, motion: FrameMotion | None) -> FrameEstimate:
        self.cnlf.begin_frame()
        estimate = super().step(frame, prev, motion)
        self.cnlf.end_frame()
        return estimate

    @property
    def relative_change(self) -> float:
        """sum |v_k - v_{k-1}|^2 / sum |v_{k-1}|^2 over the points found twice running (averaged like the evidence)."""
        change, speed = self._step_changes
        return change / speed if speed > 0 else 0.0

    def reported_cov(self) -> np.ndarray:
        """The shared error model's covariance (``calibration.py``); ``cov`` is what is handed over."""
        return self.errors.reported.copy()

    def reported_dof(self) -> np.ndarray:
        """The error model's Student-t degrees of freedom (``calibration.py``)."""
        return self.errors.dof

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        self.cnlf.start_members(index, frame, self.xy[index])
        self.on_cnlf[index] = True
        self._collect(index, self.cnlf)

    def _predictions(self, x: np.ndarray, fit, field) -> tuple[np.ndarray, np.ndarray]:
        """(n, 2) one-step predictions of (n, 2) positions x by the dominant (eq. 1) and the local (eq. 5) motion."""
        A, b = linear_dynamics(fit, x)
        return np.einsum("nij,nj->ni", A, x) + b, x + field.displacement(x)

    def _route(self, index: np.ndarray, frame: Frame, fit, field) -> np.ndarray:
        """Choose each point's filter for this step (rules 3 to 5) and hand over those that change.

        Returns the points that rule 5 moves by the dominant motion and reports not visible on this step.
        """
        margin = self.settings.evidence_margin
        e = self.evidence[index]
        want = np.where(e > margin, True, np.where(e < -margin, False, self.on_cnlf[index]))
        if self.settings.keep_local_clf:  # rule 3: the CLF already follows the local motion
            want &= self.on_cnlf[index] | ~self.clf.on_local[index]
        lost = ~self.visible[index] & np.isfinite(self.velocity[index, 0])
        if lost.any():
            x, cov = self.xy[index[lost]], self.cov[index[lost]]
            dominant, local = self._predictions(x, fit, field)
            mean_evidence, velocity = self._before_last(index[lost])
            steps = 1 + self.errors.coasted[index[lost]]  # frames since the step v was measured
            spread = extrapolation_spread(cov, velocity, steps, self.relative_change, self.q_floor)
            want[lost] = lost_on_local(x, velocity, spread, dominant, local, mean_evidence,
                                       self.settings.lost_evidence, self.on_cnlf[index[lost]], margin)
        swept = self._swept(index, fit, field)
        want &= ~swept
        to_cnlf = index[want & ~self.on_cnlf[index]]
        to_clf = index[~want & self.on_cnlf[index]]
        if to_cnlf.size:
            self.cnlf.take_over(to_cnlf, frame.index, self.xy[to_cnlf], self.cov[to_cnlf], self.visible[to_cnlf])
            self.on_cnlf[to_cnlf] = True
        if to_clf.size:
            self.clf.take_over(to_clf, frame.index, self.xy[to_clf], self.cov[to_clf], self.visible[to_clf])
            self.cnlf.release(to_clf)
            self.on_cnlf[to_clf] = False
        # A point handed to the CLF, or not found while on it, is predicted by the dominant motion (rule 4: a
        # covered point's window moves with its occluder); the CLF's own ``select`` may take it back to the
        # local motion once it is found again (filters/clf.py).
        self.clf.predict_by_dominant(to_clf)
        self.clf.predict_by_dominant(index[(lost & ~want) | swept])
        return index[swept]

    def _swept(self, index: np.ndarray, fit, field) -> np.ndarray:
        """(n,) bool, rule 5: points on the CNLF, found on the previous frame, whose measurements did not favour the
        local motion (mean evidence from before their last measurement at most ``lost_evidence``, as rule 4) and
        whose local step jumps away from their measured step (also from before their last measurement, as rule 4)
        while the dominant step continues it (:func:`swept_by_occluder`, ``occluder_jump``)."""
        swept = np.zeros(len(index), bool)
        jump = self.settings.occluder_jump
        candidates = self.on_cnlf[index] & self.visible[index] & np.isfinite(self.velocity[index, 0])
        if jump is None or not candidates.any():
            return swept
        x = self.xy[index[candidates]]
        mean_evidence, velocity = self._before_last(index[candidates])  # as rule 4 reads them
        swept[candidates] = (mean_evidence <= self.settings.lost_evidence) & swept_by_occluder(
            x, velocity, *self._predictions(x, fit, field), jump)
        return swept

    def _before_last(self, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n,) mean evidence and (n, 2) velocity of lost points ``index`` for rule 4, without their last measurement.

        A point's last measurement before it is covered is often made with its patch already half
        on the occluder, and moves with it: rule 4 reads the evidence and the step from before it,
        where the point has an earlier measured step (else from its only one).
        """
        evidence, weight, velocity = (values[index] for values in self.before_last)
        earlier = np.isfinite(velocity[:, 0]) & (weight > 0)
        mean = np.where(earlier, evidence / np.where(earlier, weight, 1.0),
                        self.evidence[index] / self.evidence_weight[index])  # weight > 0: v is finite
        return mean, np.where(earlier[:, None], velocity, self.velocity[index])

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion) -> None:
        fit, field = motion.global_fit, motion.local_field
        if self.store_segmentation:
            self.segmentation.append(np.rint(fit.weights * 255).astype(np.uint8))
        self.clf.cover(self._route(index, frame, fit, field))  # rule 5: covered, whatever the gate finds
        x_prev, cov_prev, found_prev = self.xy[index].copy(), self.cov[index].copy(), self.visible[index].copy()
        for tracker, members in ((self.clf, index[~self.on_cnlf[index]]), (self.cnlf, index[self.on_cnlf[index]])):
            tracker.advance_members(members, prev, frame, motion)
            self._collect(members, tracker)
        self._weigh(index, x_prev, cov_prev, found_prev, fit, field)

    def _weigh(self, index: np.ndarray, x_prev: np.ndarray, cov_prev: np.ndarray, found_prev: np.ndarray,
               fit, field) -> None:
        """Rule 2: update the evidence and the last measured step of the points found on this step.

        Points also found on the step before add the change of their step to ``relative_change``.
        """
        found = self.visible[index]
        a = 1.0 / self.settings.integration_frames
        self._step_changes *= 1 - a
        if not found.any():
            return
        idx = index[found]
        step = self.xy[idx] - x_prev[found]
        on_cnlf = self.on_cnlf[idx] & found_prev[found]  # the CLF notes its own points' support
        self.clf.note_support(idx[on_cnlf], self.clf.state_noise.support(fit, x_prev[found][on_cnlf]))
        again = found_prev[found] & np.isfinite(self.velocity[idx, 0])
        previous = self.velocity[idx[again]]
        change = step[again] - previous
        self._step_changes += a * np.array([np.sum(change * change), np.sum(previous * previous)])
        for kept, current in zip(self.before_last, (self.evidence, self.evidence_weight, self.velocity)):
            kept[idx] = current[idx]
        self.velocity[idx] = step
        dominant, local = self._predictions(x_prev[found], fit, field)
        spread = cov_prev[found] + self.R[idx] + self.q_floor * np.eye(2)
        self.evidence[idx] = (1 - a) * self.evidence[idx] + a * closer_to_local(self.z[idx], dominant, local, spread)
        self.evidence_weight[idx] = (1 - a) * self.evidence_weight[idx] + a

    def _collect(self, index: np.ndarray, tracker: Tracker) -> None:
        """Copy the state of points ``index`` from ``tracker`` into the router's report."""
        for name in ("xy", "cov", "visible", "seen_unmeasured", "z", "R"):
            getattr(self, name)[index] = getattr(tracker, name)[index]
        self.method_code[index] = method_code(tracker.method)

    def smooth(self, tracks: Tracks) -> Tracks:
        """Each point's CLF frames smoothed by the CLF's RTS, its CNLF frames by the CNLF's FFBSm."""
        return self.cnlf.smooth(self.clf.smooth(tracks, tracks.method == method_code(self.clf.method)))

    def finish(self, history: FrameReports) -> Tracks:
        """Tracks whose CNLF frames carry the particle path means (``CNLFTracker.path_means``).

        A frame gets the path mean fixed ``path_lag`` frames after it, or at the end, on the
        segment open then; a segment the point left before that keeps its filtering estimates.
        """
        tracks = super().finish(history)
        extras = self.cnlf.extras()
        if self.store_segmentation and self.segmentation:
            extras["segmentation"] = np.stack(self.segmentation)
        return dataclasses.replace(tracks, xy=self.cnlf.path_means(tracks.xy), extras=extras)


def make_auto(settings: AutoSettings, *, queries: Queries, info: SequenceInfo, rng: np.random.Generator,
              measure: Measurer, gamma: float, state_noise: StateNoise, smooth: bool, store_particles: bool,
              store_segmentation: bool, filter_settings: Mapping[str, StageSettings], aperture: Aperture | None = None,
              **_context) -> AutoTracker:
    """The router over a CLF and a CNLF (``filter.clf``, ``filter.cnlf`` settings) sharing one reference per point."""
    clf_settings: CLFSettings = filter_settings["clf"]
    cnlf_settings: CNLFSettings = filter_settings["cnlf"]
    p = len(queries)
    reference = ReferenceMatcher(measure, clf_settings, p, gamma)
    errors = ErrorModel(p, gamma, aperture)
    clf = CLFTracker(clf_settings, queries, info, state_noise, reference, errors, smooth)
    cnlf = CNLFTracker(cnlf_settings, queries, info, rng, reference, errors, smooth, store_particles)
    return AutoTracker(settings, queries, info, clf, cnlf, errors, state_noise.q_floor, store_segmentation)
