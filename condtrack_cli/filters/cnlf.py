"""CNLF: the conditional nonlinear filter (paper §4, §5.1 local case, Fig. 2).

Each point carries N weighted particles x^(i) (paper: N = 100). Per frame, for
all started points and all their particles at once:

- model: the local robust motion on a window around each particle gives the
  mean x^(i) + P(x^(i)) theta_k(x^(i)) =: mu^(i) and Q_k^(i) of eq. (5)
  (``motion/local/``: one shared field per frame, sampled at the particles);
  An option (``layer_jump``, off by default, docs/departures.md): a point not
  found on the previous frame whose local motion now departs from its layer's
  (a jump beyond ``layer_jump`` px and its layer's step: an occluder's field)
  is moved by its layer's motion instead, the dominant motion when it moved
  with it, else its own last measured step, both read from before its last
  measurement;
- measure: z_k and R_k in the gate, whose S is the second moment of the
  mixture sum_i w^(i) N(mu^(i), Q^(i)) (paper §5.3) about its mean;
- propagate with the optimal proposal, closed form for a linear Gaussian
  measurement (eq. 11): C = (Q^-1 + R^-1)^-1, m^(i) = C (Q^-1 mu^(i) + R^-1 z),
  x_k^(i) ~ N(m^(i), C); with no usable measurement the proposal is the
  dynamics N(mu^(i), Q^(i)) and the weights do not change;
- weight (eq. 4): log w^(i) += log N(z; mu^(i), R + Q^(i)), normalised in log space;
- resample (systematic, or residual) when the effective sample size
  1 / sum w^2 falls below ``ess_fraction`` N; ancestry is kept;
- estimate: the trajectory is the weighted mean of the particle *paths*
  x_{0:k}^(i) with the final weights (the paper's 1/N is a typo for
  normalised weights), computed in ``finish``; the reported covariance on
  each frame is the weighted covariance of that frame's particles. A
  departure (``path_points``, docs/departures.md): on each frame the path
  holds the particle's proposal mean m^(i), the mean it was drawn around
  (its expectation given its parent and z_k), not the draw itself: the same
  weights and ancestry, without the draw's own noise (Rao-Blackwellisation;
  ``particles`` is the paper's). A
  departure (``path_lag``, docs/departures.md): the estimate of frame j is
  fixed with the weights of frame j + ``path_lag`` and its particles are then
  dropped (a fixed-lag path estimate; at most ``path_lag`` + 1 frames of
  paths are held), so that memory does not grow with the clip (the paths cost
  P N 24 bytes a frame: 1.2 MB for 500 points). On a clip of at most
  ``path_lag`` + 1 frames the estimate is the paper's, bit for bit, but on the
  query frame, which reports the query: the particles' spread there
  (``initial_std``) is the filter's device, not doubt about where the point
  is (docs/departures.md, "CNLF path estimate").
With ``filter.smooth`` the CNLF records each frame's weights and the dynamics
N(mu^(i), Q^(i)) that moved the particles into it, and :meth:`CNLFTracker.smooth`
replaces the estimate by the FFBSm smoother's (``smoother.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from condtrack_cli.filters.base import Tracker
from condtrack_cli.detect.trackability import Aperture
from condtrack_cli.filters.calibration import ErrorModel
from condtrack_cli.filters.clf import local_dynamics
from condtrack_cli.filters.draws import PROPOSAL, RESAMPLING, START, PointDraws
from condtrack_cli.filters.gauss2 import inverse2, log_gauss2, matvec2, sample_gauss2
from condtrack_cli.filters.reference import ReferenceMatcher
from condtrack_cli.filters.resampling import RESAMPLERS, normalise, sum_over_particles
from condtrack_cli.filters.settings import CNLFSettings
from condtrack_cli.filters.smoother import TransitionLog, error_excess, particle_smoother, weighted_moments
from condtrack_cli.frame_reports import FrameReports
from condtrack_cli.measure.interface import Measurer
from condtrack_cli.motion.interface import FrameMotion
from condtrack_cli.motion.model import displacement
from condtrack_cli.types import FrameEstimate, Frame, Queries, SequenceInfo, Tracks


def departs(step: np.ndarray, layer: np.ndarray, jump: float) -> np.ndarray:
    """(n,) bool: the (n, 2) steps depart from their layer's (n, 2) steps by more than max(``jump`` px, the layer's
    step): an occluder's motion, not a change of the layer's own (False where either is NaN)."""
    with np.errstate(invalid="ignore"):
        return np.linalg.norm(step - layer, axis=-1) > np.maximum(jump, np.linalg.norm(layer, axis=-1))


def particle_means(info: SequenceInfo, x: np.ndarray, field, fit) -> np.ndarray:
    """(n, N, 2) one-step means of particles x (n, N, 2): x + U_local(x) (eq. 5), but x + U_dominant(x) for the
    particles off the frame and those that both motions take off it.

    Off the frame the local field has no support (the content there has left the frame) and is biased;
    the dominant motion, fitted on the whole frame, holds there (docs/departures.md). The dominant motion
    is evaluated only at the particles where it may be used (off the frame, or taken off it by the local one).
    """
    means = x + field.displacement(x)
    inside = info.contains(x)
    candidates = ~inside | ~info.contains(means)  # the particles that may be off, whatever the dominant motion does
    if candidates.any():
        dominant = x[candidates] + displacement(fit, x[candidates])
        off = candidates.copy()
        off[candidates] = ~inside[candidates] | ~info.contains(dominant)
        means[off] = dominant[off[candidates]]
    return means


def mixture_moments(log_w: np.ndarray, mu: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (n, 2) and covariance (n, 2, 2) of sum_i w^(i) N(mu^(i), Q^(i)) (the CNLF's gate, paper §5.3).

    log_w: (n, N) normalised log-weights; mu: (n, N, 2); Q: (n, N, 2, 2).
    """
    w = np.exp(log_w)[..., None]
    mean = sum_over_particles(w * mu, axis=1)
    d = mu - mean[:, None]
    spread = d[..., :, None] * d[..., None, :]  # (n, N, 2, 2) d d^T
    spread += Q
    spread *= w[..., None]
    return mean, sum_over_particles(spread, axis=1)


def propagate(
    normals: np.ndarray, log_w: np.ndarray, mu: np.ndarray, Q: np.ndarray, z: np.ndarray, R: np.ndarray,
    valid: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw the new particles from the optimal proposal and update the weights (Fig. 2).

    normals (n, N, 2): standard normal draws; log_w (n, N) normalised; mu (n, N, 2) = x + P(x) theta(x);
    Q (n, N, 2, 2); z (n, 2); R (n, 2, 2) finite; valid (n,): where False, the proposal is the
    dynamics N(mu, Q) and the weights stay. Returns particles (n, N, 2),
    normalised log-weights (n, N) and the proposal means m (n, N, 2) the particles were drawn around.
    """
    R, z = R[:, None], z[:, None]  # (n, 1, 2, 2), (n, 1, 2): the same for all particles of a point
    q_inv, r_inv = inverse2(Q), inverse2(R)
    C = inverse2(q_inv + r_inv)  # eq. (11): C_k = (Q^-1 + R^-1)^-1
    m = matvec2(C, matvec2(q_inv, mu) + matvec2(r_inv, z))  # eq. (11): m = C (Q^-1 mu + R^-1 z)
    unmeasured = ~valid
    m[unmeasured], C[unmeasured] = mu[unmeasured], Q[unmeasured]
    particles = sample_gauss2(m, C, normals)
    with np.errstate(invalid="ignore"):  # the rows without a measurement (z NaN or outside the gate) are not used
        log_like = log_gauss2(z, mu, R + Q)  # eq. (4): p(z | x_{k-1}) = N(z; mu, R + Q)
    return particles, normalise(np.where(valid[:, None], log_w + log_like, log_w)), m


def resample(uniform: np.ndarray, particles: np.ndarray, log_w: np.ndarray,
             settings: CNLFSettings) -> tuple[np.ndarray, np.ndarray]:
    """Resample in place the rows of particles (n, N, 2) and normalised log-weights (n, N) whose effective sample
    size 1 / sum w^2 is below ess_fraction N: their particles are drawn among their own (``settings.resampling``,
    with the rows' (n,) ``uniform`` draws in [0, 1)) and their weights reset to uniform; the other rows are left
    as they are (each particle its own parent).
    Returns those rows (m,) and their ancestor indices (m, N).
    """
    count = log_w.shape[1]
    weights = np.exp(log_w)
    degenerate = np.flatnonzero(1.0 / (weights**2).sum(axis=1) < settings.ess_fraction * count)
    picks = (RESAMPLERS[settings.resampling](weights[degenerate], uniform[degenerate]) if degenerate.size
             else np.zeros((0, count), int))
    particles[degenerate] = np.take_along_axis(particles[degenerate], picks[..., None], axis=1)
    log_w[degenerate] = -np.log(count)
    return degenerate, picks


class CNLFTracker(Tracker):
    """Particle filter with the optimal proposal, vectorised over points and particles: arrays (P, N, ...)."""

    method = "cnlf"
    needs_motion = True
    needs_local_motion = True

    def __init__(self, settings: CNLFSettings, queries: Queries, info: SequenceInfo, rng: np.random.Generator,
                 reference: ReferenceMatcher, errors: ErrorModel, smooth: bool, store_particles: bool):
        """rng: the pass's source of random draws (it keys :class:`PointDraws`); reference: the points' reference
        patches and gate; errors: the reported covariance's model; smooth: record what :meth:`smooth` needs
        (``filter.smooth``); store_particles: :meth:`extras` returns them."""
        super().__init__(queries, info)
        self.settings, self.draws = settings, PointDraws(rng, queries.point_id)
        self.reference, self.errors = reference, errors
        p, n = len(queries), settings.particles
        self.particles = np.full((p, n, 2), np.nan)
        #: (P, N, 2) the mean each current particle was drawn around (eq. 11; at a (re)start, the draw itself)
        self.proposal_means = np.full((p, n, 2), np.nan)
        self.log_w = np.full((p, n), -np.log(n))
        self.lineage_start = np.full(p, -1)  #: pass frame at which each point's particles were (re)drawn
        #: per kept frame, (P, N, 2) the positions the path estimate averages (``path_points``), NaN off the CNLF
        self.path_history: list[np.ndarray] = []
        self.keep_particles = store_particles or smooth  #: the particles of every frame are kept (particle_history)
        self.particle_history: list[np.ndarray] = []  #: per frame, (P, N, 2) particles, NaN off the CNLF, if kept
        self.store_particles = store_particles
        #: per kept frame, the points resampled into it (m,) and the index of each of their particles' parent (m, N);
        #: every other particle is its own parent
        self.ancestor_history: list[tuple[np.ndarray, np.ndarray]] = []
        self.first_kept = 0  #: pass frame of path_history[0]; the frames before have a fixed path estimate
        self.fixed_paths: list[np.ndarray] = []  #: per frame before first_kept, (P, 2) path estimate, NaN off a lineage
        #: frame k - path_lag is fixed and dropped after frame k, unless all are wanted (stored particles, the smoother)
        self.lag = None if settings.path_lag is None or self.keep_particles else settings.path_lag
        self.transitions = TransitionLog(p, log_w=(n,), mu=(n, 2), Q=(n, 2, 2), excess=(2, 2)) if smooth else None
        #: each point's layer as last read, from before its last measurement (``_layer_motion``), and as measured
        #: then: its step (px/frame, NaN: none yet) and whether it moved with the dominant motion
        self.layer_step, self.layer_dominant = np.full((p, 2), np.nan), np.zeros(p, bool)
        self.measured_step, self.measured_dominant = np.full((p, 2), np.nan), np.zeros(p, bool)

    def step(self, frame: Frame, prev: Frame | None, motion: FrameMotion | None) -> FrameEstimate:
        self.begin_frame()
        estimate = super().step(frame, prev, motion)
        self.end_frame()
        return estimate

    def begin_frame(self) -> None:
        """Before a frame: no particle has been resampled yet (each is its own parent)."""
        self.errors.begin_frame()
        self.ancestors = (np.zeros(0, int), np.zeros((0, self.settings.particles), int))

    def end_frame(self) -> None:
        """After a frame: keep its path points (``path_points``) and the particles' parents for the path estimate, and
        its particles where they are kept; fix the frame that falls out."""
        on = (self.lineage_start >= 0)[:, None, None]
        of_means = self.settings.path_points == "proposal_means"
        path = np.where(on, self.proposal_means if of_means else self.particles, np.nan)
        self.path_history.append(path)
        if self.keep_particles:  # every frame's (the lag is off then); the path's own array when it holds them
            self.particle_history.append(np.where(on, self.particles, np.nan) if of_means else path)
        self.ancestor_history.append(self.ancestors)
        if self.transitions is not None:
            self.transitions.record(len(self.path_history) - 1, np.arange(len(self.log_w)), log_w=self.log_w.copy())
        if self.lag is not None and len(self.path_history) > self.lag:
            self.fixed_paths.append(self._path_estimates(stop=1)[0])
            del self.path_history[0], self.ancestor_history[0]
            self.first_kept += 1

    def adopt(self, index: np.ndarray, frame_index: int, xy: np.ndarray, cov: np.ndarray) -> None:
        """(Re)start points ``index`` with particles drawn from N(xy (n, 2), cov (n, 2, 2)), equal weights."""
        n = self.settings.particles
        normals = self.draws.normal_pairs(frame_index, START, index, n)
        self.particles[index] = sample_gauss2(np.repeat(xy[:, None], n, 1), np.repeat(cov[:, None], n, 1), normals)
        self.proposal_means[index] = self.particles[index]
        self.log_w[index] = -np.log(n)
        self.lineage_start[index] = frame_index
        self.layer_step[index] = self.measured_step[index] = np.nan  # no layer known until measured twice running
        self._report(index, self.particles[index], self.log_w[index])

    def take_over(self, index: np.ndarray, frame_index: int, xy: np.ndarray, cov: np.ndarray,
                  visible: np.ndarray) -> None:
        """Points ``index`` handed over from another filter: particles drawn from N(xy, cov) (:meth:`adopt`)."""
        self.adopt(index, frame_index, xy, cov)
        self.visible[index] = visible

    def release(self, index: np.ndarray) -> None:
        """Points ``index`` leave this filter: their frames keep the estimates already reported."""
        self.lineage_start[index] = -1

    def _start(self, index: np.ndarray, frame: Frame) -> None:
        self.reference.start(index, frame, self.xy[index])
        s = self.settings
        self.adopt(index, frame.index, self.xy[index], np.repeat(s.initial_std**2 * np.eye(2)[None], index.size, 0))
        self.errors.start(index, self.cov[index], frame.gray, self.xy[index])

    def reported_cov(self) -> np.ndarray:
        """The error model's covariance (``calibration.py``), not the particles' spread alone."""
        return self.errors.reported.copy()

    def reported_dof(self) -> np.ndarray:
        """The error model's Student-t degrees of freedom (``calibration.py``)."""
        return self.errors.dof

    def _report(self, index: np.ndarray, particles: np.ndarray, log_w: np.ndarray) -> None:
        """xy and cov of points ``index``: the weighted mean and covariance of their current particles (n, N, 2)
        with normalised log-weights (n, N)."""
        self.xy[index], self.cov[index] = weighted_moments(particles, log_w)

    def _advance(self, index: np.ndarray, prev: Frame, frame: Frame, motion: FrameMotion) -> None:
        x_prev = self.xy[index].copy()
        found_before = self.visible[index].copy()
        field = motion.local_field
        x = self.particles[index]  # (n, N, 2)
        mu = particle_means(self.info, x, field, motion.global_fit)  # eq. (5) mean, the dominant motion off the frame
        covered = self._covered(index, x_prev, found_before, field, motion.global_fit)
        if covered.any():
            mu[covered] = x[covered] + self._layer_displacement(index[covered], x[covered], motion.global_fit)
        Q = field.noise(x)  # (n, N, 2, 2)
        gate_mean, gate_cov = mixture_moments(self.log_w[index], mu, Q)
        if self.settings.warp_reference:  # the neighbourhood's deformation by the local field
            self.reference.deform(index, local_dynamics(field, x_prev)[0])
        measured = self.reference.measure_in_gate(index, frame, gate_mean, gate_cov, prev, x_prev, found_before,
                                                  self.errors.coasted[index])
        mu = mu + measured.shift[:, None]  # the mixture moved where the fallback centre's match is used (``lk_fallback``)
        gate_mean = gate_mean + measured.shift
        if self.transitions is not None:  # particles drawn this frame from the previous one's: smoothable
            linked = self.lineage_start[index] < frame.index
            self.transitions.record(frame.index, index[linked], mu=mu[linked], Q=Q[linked])
        normals = self.draws.normal_pairs(frame.index, PROPOSAL, index, self.settings.particles)
        particles, log_w, means = propagate(normals, self.log_w[index], mu, Q, measured.z, measured.R_used,
                                            measured.valid)
        resampled, picks = resample(self.draws.uniform(frame.index, RESAMPLING, index)[:, 0], particles, log_w,
                                    self.settings)
        means[resampled] = np.take_along_axis(means[resampled], picks[..., None], axis=1)  # each particle's own
        self.proposal_means[index] = means
        self.ancestors = (index[resampled], picks)
        self.particles[index], self.log_w[index] = particles, log_w
        self._report(index, particles, log_w)
        self.visible[index], self.seen_unmeasured[index] = measured.valid, measured.seen_unmeasured
        self.z[index], self.R[index] = measured.z, measured.R
        retaken = self.reference.refresh(index, prev, x_prev, frame, self.xy[index], found_before, measured)
        disagreement = field.displacement(x_prev) - displacement(motion.global_fit, x_prev)
        self._remember_layer(index, x_prev, found_before, measured.valid, motion.global_fit)
        self.errors.update(index, gate_mean, gate_cov, measured.z, measured.R_used, measured.valid, self.xy[index],
                           self.cov[index], retaken, disagreement,
                           self.reference.offset_floor[index], measured.jump)
        if self.transitions is not None:
            self.transitions.record(frame.index, index, excess=self.errors.reported[index] - self.cov[index])

    def _layer_displacement(self, index: np.ndarray, x: np.ndarray, fit) -> np.ndarray:
        """(n, N, 2) one-step displacement of particles x (n, N, 2) of points ``index`` by their layer's motion:
        the dominant motion where the point moved with it, else its last measured step."""
        dominant = displacement(fit, x.reshape(-1, 2)).reshape(x.shape)
        own = np.broadcast_to(self.layer_step[index, None], x.shape)
        return np.where(self.layer_dominant[index, None, None], dominant, own)

    def _covered(self, index: np.ndarray, x_prev: np.ndarray, found_before: np.ndarray, field, fit) -> np.ndarray:
        """(n,) bool: points not found on the previous frame whose local motion at their estimate x_prev (n, 2)
        departs from their layer's by more than max(``layer_jump``, the layer's step) px."""
        jump = self.settings.layer_jump
        if jump is None:
            return np.zeros(len(index), bool)
        known = ~found_before & np.isfinite(self.layer_step[index, 0])
        layer = self._layer_displacement(index, x_prev[:, None], fit)[:, 0]
        return known & departs(field.displacement(x_prev), layer, jump)

    def _remember_layer(self, index: np.ndarray, x_prev: np.ndarray, found_before: np.ndarray, found: np.ndarray,
                        fit) -> None:
        """After a step: points found on both frames have a measured step; the one before it becomes their layer's.

        The layer is read from before the last measurement: a point about to be covered is often last
        measured with its patch half on its occluder, and that step moves with the occluder.
        """
        both = index[found_before & found]
        if not both.size:
            return
        step = self.xy[both] - x_prev[found_before & found]
        dominant = displacement(fit, x_prev[found_before & found])
        close = np.linalg.norm(step - dominant, axis=1) <= np.maximum(1.0, 0.1 * np.linalg.norm(dominant, axis=1))
        earlier = np.isfinite(self.measured_step[both, 0])
        self.layer_step[both] = np.where(earlier[:, None], self.measured_step[both], step)
        self.layer_dominant[both] = np.where(earlier, self.measured_dominant[both], close)
        self.measured_step[both], self.measured_dominant[both] = step, close

    def finish(self, history: FrameReports) -> Tracks:
        """The trajectory estimate: the weighted mean of the particle paths with the final weights."""
        tracks = super().finish(history)
        return dataclasses.replace(tracks, xy=self.path_means(tracks.xy), extras=self.extras())

    def smooth(self, tracks: Tracks) -> Tracks:
        """``tracks`` with the FFBSm mean and covariance on every frame where the point has particles."""
        n_frames = tracks.xy.shape[1]
        particles = np.stack(self.particle_history, axis=1)  # (P, F, N, 2)
        mu = self.transitions.stacked("mu", n_frames)
        linked = np.isfinite(mu).all(axis=(2, 3))
        xy, cov = particle_smoother(
            particles, self.transitions.stacked("log_w", n_frames), mu, self.transitions.stacked("Q", n_frames), linked,
        )
        on = np.isfinite(particles).all(axis=(2, 3))
        cov = cov + error_excess(self.transitions.stacked("excess", n_frames))
        return dataclasses.replace(
            tracks, xy=np.where(on[..., None], xy, tracks.xy), cov=np.where(on[..., None, None], cov, tracks.cov),
        )

    def extras(self) -> dict:
        """``particles/xy`` (P, F, N, 2) float32 when ``output.store_particles`` is set."""
        if not self.store_particles:
            return {}
        return {"particles/xy": np.stack(self.particle_history, axis=1).astype(np.float32)}

    def _path_estimates(self, stop: int) -> list[np.ndarray]:
        """(P, 2) weighted path means with the current weights on the kept frames first_kept .. first_kept + stop - 1.

        Paper Fig. 2, T = sum_i x_{0:k}^(i) w_k^(i): each current particle's ancestor on the frame (its position
        there as ``path_points`` says), weighted by the particle's weight; NaN for the points whose current lineage
        started after the frame.
        """
        weights = np.exp(self.log_w)[..., None]  # (P, N, 1)
        lineage = np.broadcast_to(np.arange(self.settings.particles), self.log_w.shape).copy()
        resampled = np.zeros(len(self.log_w), bool)  # the points whose lineage is not the identity
        means = []
        for j in range(len(self.path_history) - 1, -1, -1):
            if j < stop:
                inside = (self.lineage_start <= self.first_kept + j) & (self.lineage_start >= 0)
                paths = self.path_history[j][inside]  # (n, N, 2): each current particle's ancestor at j
                moved = np.flatnonzero(resampled[inside])
                paths[moved] = np.take_along_axis(paths[moved], lineage[inside][moved, :, None], axis=1)
                mean = np.full((len(self.log_w), 2), np.nan)
                with np.errstate(invalid="ignore"):
                    mean[inside] = sum_over_particles(weights[inside] * paths, axis=1)
                means.append(mean)
            points, picks = self.ancestor_history[j]
            lineage[points] = np.take_along_axis(picks, lineage[points], axis=1)
            resampled[points] = True
        return means[::-1]

    def path_means(self, xy: np.ndarray) -> np.ndarray:
        """(P, F, 2) ``xy`` with the path estimates on the frames of each point's particle lineage.

        The frames still kept get the weighted path means with the final weights; the earlier ones the
        estimate fixed ``path_lag`` frames after them; the query frame the query (module docstring).
        """
        xy = xy.copy()
        estimates = self.fixed_paths + self._path_estimates(stop=len(self.path_history))
        for j, mean in enumerate(estimates):
            on = np.isfinite(mean[:, 0])
            xy[on, j] = mean[on]
        started = np.flatnonzero(self.queries.frame < xy.shape[1])  # a clip may end before a query
        xy[started, self.queries.frame[started]] = self.queries.xy[started]  # the query frame: the query itself
        return xy


def make_cnlf(settings: CNLFSettings, *, queries: Queries, info: SequenceInfo, rng: np.random.Generator,
              measure: Measurer, gamma: float, smooth: bool, store_particles: bool, aperture: Aperture | None = None,
              **_context) -> CNLFTracker:
    reference = ReferenceMatcher(measure, settings, len(queries), gamma)
    return CNLFTracker(settings, queries, info, rng, reference, ErrorModel(len(queries), gamma, aperture), smooth,
                       store_particles)
