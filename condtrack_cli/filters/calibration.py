"""The reported covariance: the filter's covariance corrected by what its innovations and its reference updates show.

The covariance a filter carries (CLF: the Kalman posterior; CNLF: the particles'
spread) serves its gate and its gain. As a statement about the error to the true
point it misses three things, measured on the shared real sets (issue 12;
kt3dmoseg_seq005, CLF): the innovations nu = z_k - x_{k|k-1} of found points are
smaller than S = Sigma_{k|k-1} + R_k says (mean NIS 0.54 where a consistent
filter gives 2: R_k of eqs. 8-10 and Q_k are conservative one step ahead); the
reference patch is re-taken at the estimate on about half of the found frames
(``reference.py``), so the error of each re-take stays in every later
measurement (a random walk the filter does not model: the error of points never
lost grew from 0.16 px median one frame after the query to 0.99 px after 8 while
the filter's std stayed 0.6 px); and a point that is not found coasts on a
dynamics that misses it by a similar amount every frame (parallax), so its error
grows linearly with the frames coasted (median 1.7 px after one frame, 10 px
after 8), not as the square root the filter's Q_k gives.

The model, per point, reported covariance = g (max(lambda, 1) Sigma + D + W + C):

- lambda: innovation-based consistency of the filter's covariance (covariance
  matching): the mean NIS nu^T S^-1 nu of the found points over recent frames,
  divided by its expectation 2 (chi-square, 2 dof); pooled over the points (one
  point's NIS is far too noisy), forgotten with factor ``FORGET`` per frame.
  Sigma is inflated by lambda when lambda > 1, never shrunk: the innovations
  cannot see an error that prediction and measurement share (the bias of a
  deforming template, which Sigma's R_k does carry: on the camera_motion sample
  lambda Sigma alone held the truth in 19 % of the 95 % ellipses, Sigma in 98 %).
  Where Sigma is only a one-step statement (D and the gate's coverage below),
  lambda Sigma is used as it is.
- D: the covariance of the offset between the current reference patch and the
  true point, which later measurements of that patch cannot reduce. 0 at the
  query of a trackable point; a query that fails the trackability test (issue
  29: a flat region, an edge) starts with its aperture offset
  (``detect.trackability.Aperture``): its patch matches as well anywhere along
  the aperture, so it may lock on a spot that is not the point.
  Each match adds the spread of a wrong match with its probability (PDA, one
  candidate): with B = lambda Sigma_{k|k-1} + C' the covariance of where the
  patch may be, the patch lies in the gate {nu^T S^-1 nu <= gamma} with prior
  probability about 1 - w0, w0 = exp(-gamma tr S / (2 tr B)) (isotropic
  approximation). The innovation then tells a right match from a wrong one: a
  right match puts nu ~ N(0, F), F = lambda S + t^2 q I the one-step miss of the
  motion followed (t, q as in C, t the frames coasted before this one), a wrong
  one (the best SSD on something else) anywhere in the gate, density 1 / (pi
  gamma sqrt|S|); so P(wrong | nu) = w0 / (w0 + (1 - w0) pi gamma sqrt|S| N(nu; 0, F)),
  and D gains P(wrong | nu) (B + s s^T), s the step the update made. C' is C
  (below) with d including this frame's disagreement: a point found on every
  frame may still have followed either motion over this one, so where the local
  and the dominant motion part by much more than the gate, a match in the gate
  may be on the patch the other motion carried there. The prior alone (before
  this innovation term) did not tell good matches from bad ones: on
  kt3dmoseg_seq059 (CLF) a match with prior w0 >= 0.5 jumped the error by more
  than 3 px on 10 % of the frames, one with w0 < 0.01 on 0.2 %, while on
  oxford_merton1 w0 averaged 0.66 on found rows whose error was 0.43 px
  median. The NIS of the match separates them: NIS < 0.5 jumped 0.3-1.5 % of
  the time, NIS > 5 12-36 % (seq005, seq059, dinosaur, merton1). With the
  innovation term, found rows of P(wrong | nu) < 0.01 jumped 0-1.7 %, those
  of P >= 0.5 12-29 %.
  J (issue 45): a point found again by the re-acquisition (``reference.py``,
  ``_reacquire``: a search around where it was last found, tens of pixels from
  its prediction) adds j j^T to D, j = z - the prediction, the jump: the
  match's prior and innovation above are those of the gate around the search's
  result, and say nothing of the jump. No measure tells the re-acquisition's
  right finds from its wrong ones (nearly all wrong on KITTI, all right on
  dudek_03: docs/departures.md, "The re-acquisition's jump", has the counts),
  so the point is either where the find put it or about where it was
  predicted: a bounded either-or, j j^T its second moment, part of A.
  R (issue 45): a point found again after coasting (t >= 1 frames not found).
  The gate it is matched in lies around where coasting took it; if the match is
  a look-alike there, the point is about where its coasting left it, within C'
  of the prediction, not anywhere: that part of the wrong-match share,
  P(wrong | nu) C', is a bounded either-or and joins A (its second moment is
  already in the share; the rest of the share stays a tail). Without it a point
  lost behind a hand and matched again on a look-alike (dudek_03's point 2,
  27-30 px off) kept a 95 % ellipse of 11-14 px (134-172 px with it; read once
  from the seed-0 track file of ``bench --versus-lk``), and the
  faces' and the camel's 90 and 95 % ellipses held too little (docs/departures.md,
  "A point found again after coasting").
- W: the walk of the reference's offset (issue 45). Each re-take of the reference
  (``reference.py``, ``refresh``) adds lambda Sigma_post, the error of the position
  it was taken at, which every later match of the new patch repeats. A re-take that
  the point's first patch does not confirm within ``drift_check`` px (``_anchored``:
  the first patch no longer matches there, its appearance has changed or the chain
  of re-takes has left it) lifts W to at least ``drift_check``^2 / 4 on each axis
  (``offset_floor``): nothing then holds the offset below that reach, and an offset
  spread evenly over the disk of radius ``drift_check`` has that per-axis variance
  (with the full ``drift_check``^2, KITTI's 50 % ellipses held 0.645 of the truth,
  group mean of ``auto``; 0.621 with the quarter; bench/history.md). A re-take the
  first patch does confirm is made at that patch's match, r px from the estimate:
  the chain of re-takes and the first patch then disagree by r, and nothing tells
  which is right (the first patch's appearance has changed too), so W is lifted to
  at least r^2 / 4 per axis, the same disk's variance with the radius measured
  (issue 45: docs/departures.md, "The re-take walk W"). On the face clips the re-takes
  are made on 70-90 % of the frames (the match's residual is 50-80 times the
  noise's), so W, not D, is most of their error: a steady offset of a few pixels.
- C: the coasting excess, 0 on a found frame. While a point is not found for t
  frames its error grows by the dynamics' one-step miss every frame, in the same
  direction (a constant velocity error): t^2 q I, q the per-axis mean squared
  innovation |nu|^2 / 2 of the found points (pooled as lambda); plus
  |d|^2 / 2 I, d the sum over the frames coasted of the local minus the
  dominant motion's prediction at the point: the two dynamics' disagreement
  measures how far the dynamics can miss the point (a covered point's window
  moves with its occluder; on parallax either may be right, or neither), the
  second moment of the equal-weight mixture of the two about the one followed,
  taken isotropic because the miss need not lie along d: on the Oxford sets the
  coasting rows' error was 0.44-0.83 |d| (median) in any direction, and d d^T / 2
  held the truth in the 95 % ellipse on 0.39 (merton1) and 0.79 (dinosaur) of
  them.

- g: the growth by the point's own innovations (issue 45, "Growth" below).

Growth. The terms above are pooled over the points (lambda, q) or read from one
frame's match (D); a point whose own matches jump about more than its filter
expects (a face that turns, an animal's joint whose skin slides, a patch that
no longer fits) has errors far beyond them. Its innovation consistency
lambda_p measures that on its own frames: its NIS / 2 over its found frames,
forgotten with ``FORGET`` per frame as the pooled lambda, joined by
``POINT_PRIOR`` frames at the pooled lambda (``consistency``). On every group
of shared real sets the rows with the larger lambda_p are the ones whose 95 %
ellipse missed the truth more often (docs/departures.md, "The covariance grown
by the point's own innovations", has the diagnosis and its numbers). So the
whole reported covariance is grown by g = clip((lambda_p /
``GROWTH_KNEE``)^``GROWTH_POWER``, 1, ``GROWTH_MAX``), and the Student-t's core
tightened to match (``RATIO_OWN``). g is never below 1: a point's innovations
cannot see what prediction and measurement share (letting g fall below 1 made
a synthetic scene's 95 % ellipses far too small; same section). At the query
(no innovation yet) g is 1.

The error is heavy-tailed against the reported covariance (a mixture of right
and wrong matches summarised by its second moment): on the seven shared real
sets (``bench --versus-lk``, the Gaussian reading ``cov50_gauss`` ...; clf, cnlf,
auto) the 95 % Gaussian ellipse held the truth on 0.932-0.997 of the rows and the
99 % one on 0.953-1.000, but the 50 % one on 0.786-0.978: the core is too wide
(bench/results.md, "Calibration, Student-t").

Student-t (issue 27). Each row's predictive distribution is a bivariate
Student-t whose covariance is the reported one above (unchanged: it stays the
second moment, never below max(lambda, 1) Sigma) and whose scale matrix is rho
times it, so nu = 2 / (1 - rho) (covariance = scale nu / (nu - 2)). rho is
where the row's errors have their core against their second moment, taken term
by term and weighted by each term's trace (``scale_ratio``):

- the filter's own max(lambda, 1) Sigma: ``RATIO_OWN``. The errors' core is a
  small part of their second moment here too: the innovations that set lambda
  are far inside S on most points (mean NIS 0.54), and a few points' large
  misses make the second moment. (Until issue 45 this ratio followed the point's
  own lambda_p; lambda_p now grows the covariance instead, "Growth" above, and
  with the growth a ratio that follows lambda_p fitted no better than a constant);
- the bounded part A of D: the aperture offset (a query that failed the
  trackability test), a bounded slide along an edge, the jumps of the
  re-acquisitions (J above) and the returns' coasting spread (R above), each a
  bounded either-or: ``RATIO_BOUNDED`` 1, not a tail;
- the walk W: ``RATIO_WALK``, a sum of many re-takes' offsets, most of them
  small (chosen by hand at 0.3 before the growth, bench/history.md; fitted with
  it, a tight core in a growing second moment);
- the rest of D (wrong matches): ``RATIO_DRIFT`` times n_D, and the coasting
  C: ``RATIO_COAST``: both are mixtures of rare large errors and many small
  ones summarised by their second moment, so their core is a small part of it.
  D is a sum over the frames of each frame's share of a wrong match; n_D =
  (sum c_k)^2 / sum c_k^2 (c_k the trace of frame k's share, n_D 1 before the
  first) is the number of comparable shares it sums: one frame's wrong match is
  a rare large error, a point whose matches are doubtful frame after frame (an
  animal's joint whose skin slides) sums many, and a sum of n independent rare
  errors has n times their chance of having occurred: its core is about n times
  as large a part of it (to first order; issue 45: docs/departures.md, "The
  wrong-match term's core").

rho is kept in [``RATIO_MIN``, 0.999]. The ratios and the growth were fitted
together (issue 45; a one-off random search over per-row terms of the runs of
``auto``, ``clf`` and ``cnlf``, not part of the project; bench/history.md) to the
issue's bands by group and method: the five KITTI clips, the four face clips,
the two Oxford sets (KITTI and Oxford weighted tenfold: their bands were met
before), the camel's 95 %, and the synthetic scenes of seeds 1 and 2
(``condtrack synth`` at their defaults, exact truth); each group's mean
coverage at 50 / 90 / 95 / 99 % and each set's 50 and 95 %. Of the seed-0
scenes, which ``bench --versus-lk`` reports, only tests/test_calibration.py's
bounds on the shipped camera_motion (clf, cnlf) and occlusion (cnlf) samples
were constraints; the other seed-0 coverages were held out.
``bench --versus-lk`` prints the coverage per set and scene (bench/results.md).

The filter's own state (its covariance, gate and gain) is unchanged, so positions
are those of the filter without the model, bit for bit; ``filter.smooth`` smooths
the filter's own covariance and adds back each frame's excess
(``smoother.error_excess``).
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.detect.trackability import Aperture
from condtrack_cli.filters.gauss2 import log_gauss2
from condtrack_cli.special import expit

#: Weight kept by the pooled innovation statistics from one frame to the next.
FORGET = 0.5

#: The Student-t's scale over its covariance, per term of the reported covariance (module docstring, "Student-t"):
#: the filter's own max(lambda, 1) Sigma, the bounded part A of D, the rest of D, the coasting C and the walk W.
#: Fitted together with the growth below (RATIO_BOUNDED kept) by group and method (issue 45; module docstring);
#: RATIO_COAST refitted alone with R (0.0871 before it; docs/departures.md, "A point found again after coasting");
#: RATIO_OWN refitted alone with the CNLF's path estimate of proposal means (0.103 before it; docs/departures.md,
#: "CNLF path estimate: the proposal means").
RATIO_OWN = 0.075
RATIO_BOUNDED = 1.0
RATIO_DRIFT = 0.0005
RATIO_COAST = 0.01
RATIO_WALK = 0.0605
#: Least ratio of a row (nu >= 2 / (1 - RATIO_MIN)).
RATIO_MIN = 0.00108

#: The point's own innovations grow its reported covariance (module docstring, "Growth"): by
#: clip((lambda_p / GROWTH_KNEE)^GROWTH_POWER, 1, GROWTH_MAX).
GROWTH_KNEE = 0.0304
GROWTH_POWER = 0.601
GROWTH_MAX = 16.8

#: Pseudo-count of the pooled lambda in each point's own lambda_p (found frames, forgotten as the pooled sums).
POINT_PRIOR = 1.0


def scale_ratio(own: np.ndarray, bounded: np.ndarray, drift: np.ndarray, coast: np.ndarray,
                walk: np.ndarray | float = 0.0, drift_shares: np.ndarray | float = 1.0) -> np.ndarray:
    """(n,) rho = tr(Student-t scale) / tr(covariance) of rows whose reported covariance is the sum of the traces
    ``own`` (the filter's, lambda-scaled), ``bounded`` (A), ``drift`` (D - A), ``coast`` (C) and ``walk`` (W), all
    (n,) px^2 (``walk`` 0: none), times any growth (which leaves rho alone); ``drift_shares`` (n,) n_D >= 1, the
    number of comparable frame shares D - A sums (module docstring, "Student-t"); in (0, 1)."""
    total = own + bounded + drift + coast + walk
    scale = (RATIO_OWN * own + RATIO_BOUNDED * bounded + RATIO_DRIFT * drift_shares * drift + RATIO_COAST * coast
             + RATIO_WALK * walk)
    return np.clip(scale / np.where(total > 0, total, np.inf), RATIO_MIN, 0.999)


def tail_dof(ratio: np.ndarray) -> np.ndarray:
    """(n,) Student-t nu whose scale matrix is ``ratio`` (n,) times its covariance: nu / (nu - 2) = 1 / ratio."""
    return 2.0 / (1.0 - ratio)


class ErrorModel:
    """Per-point terms of the reported covariance of P points (module docstring); arrays (P, ...)."""

    def __init__(self, n_points: int, gamma: float, aperture: Aperture | None = None):
        """aperture: the trackability test's window and floor, the queries' initial D (None: no initial D)."""
        self.gamma = gamma  #: the gate's chi-square threshold
        self.aperture = aperture
        self.drift = np.zeros((n_points, 2, 2))  #: D, px^2
        #: (P, 2) sum c_k and sum c_k^2 of the traces c_k of the frames' shares of D - A (px^2, px^4): n_D's sums
        self.drift_share_sums = np.zeros((n_points, 2))
        self.walk = np.zeros((n_points, 2, 2))  #: W, px^2
        self.coasted = np.zeros(n_points)  #: t, frames since the point was last found
        self.detour = np.zeros((n_points, 2))  #: sum over the frames coasted of the dynamics' disagreement, px
        self.reported = np.full((n_points, 2, 2), np.nan)  #: the covariance reported, px^2
        #: A, the bounded part of D: the aperture offset a query started with and the re-acquisitions' J, px^2
        self.bounded = np.zeros((n_points, 2, 2))
        self.ratio = np.full(n_points, np.nan)  #: rho, the Student-t's scale over the reported covariance
        self._nis = np.zeros(2)  #: forgotten sums of NIS and of the count of found points
        self._miss = np.zeros(2)  #: forgotten sums of |nu|^2 and of the count
        self._point_nis = np.zeros((n_points, 2))  #: each point's forgotten sums of NIS and of its found frames

    @property
    def scale(self) -> float:
        """lambda: pooled mean NIS / 2 (1 before any point was found)."""
        return self._nis[0] / (2.0 * self._nis[1]) if self._nis[1] > 0 else 1.0

    @property
    def consistency(self) -> np.ndarray:
        """(P,) lambda_p: each point's forgotten mean NIS / 2, its sums joined by ``POINT_PRIOR`` found frames at the
        pooled lambda (so a point never found has the pooled lambda)."""
        prior = POINT_PRIOR * self.scale
        return (self._point_nis[:, 0] / 2.0 + prior) / (self._point_nis[:, 1] + POINT_PRIOR)

    @property
    def growth(self) -> np.ndarray:
        """(P,) g = clip((lambda_p / GROWTH_KNEE)^GROWTH_POWER, 1, GROWTH_MAX): the factor on each point's reported
        covariance from its own innovations (module docstring, "Growth")."""
        return np.clip((self.consistency / GROWTH_KNEE) ** GROWTH_POWER, 1.0, GROWTH_MAX)

    @property
    def miss(self) -> float:
        """q: pooled per-axis mean squared innovation (px^2; 0 before any point was found)."""
        return self._miss[0] / (2.0 * self._miss[1]) if self._miss[1] > 0 else 0.0

    def start(self, index: np.ndarray, sigma: np.ndarray, gray: np.ndarray | None = None,
              xy: np.ndarray | None = None) -> None:
        """Points ``index`` start at (n, 2) ``xy`` on the (H, W) frame ``gray`` with covariance (n, 2, 2) ``sigma``,
        not coasting, D their aperture offset (0 where they pass the trackability test, or without ``gray``)."""
        offset = self.aperture.offset(gray, xy, sigma) if self.aperture is not None and gray is not None else 0.0
        self.drift[index] = offset
        self.drift_share_sums[index] = 0.0
        self.walk[index] = 0.0
        self.bounded[index] = offset
        self._point_nis[index] = 0.0
        self.coasted[index] = 0
        self.detour[index] = 0.0
        self._report(index, sigma, self.drift[index], np.zeros_like(self.drift[index]), grow=False)

    def _report(self, index: np.ndarray, own: np.ndarray, drift: np.ndarray, coast: np.ndarray,
                grow: bool = True) -> None:
        """Reported covariance of points ``index``: the filter's (n, 2, 2) ``own`` plus the (n, 2, 2) ``drift`` D and
        ``coast`` C and the walk W, times each point's ``growth`` (``grow``; else as they are: at the query); and the
        Student-t's scale over it (``scale_ratio``, which the growth leaves alone), A taken as the part of D it still
        is."""
        walk = self.walk[index]
        factor = self.growth[index] if grow else np.ones(len(index))
        self.reported[index] = factor[:, None, None] * (own + (drift + coast) + walk)
        own, drift, coast, offset, walk = (np.trace(m, axis1=1, axis2=2)
                                     for m in (own, drift, coast, self.bounded[index], walk))
        bounded = np.minimum(offset, drift)
        self.ratio[index] = scale_ratio(own, bounded, drift - bounded, coast, walk, self.drift_shares(index))

    def drift_shares(self, index: np.ndarray) -> np.ndarray:
        """(n,) n_D = (sum c_k)^2 / sum c_k^2 >= 1 of points ``index``: how many comparable frame shares c_k their
        D - A sums (module docstring, "Student-t"); 1 before the first share."""
        total, squares = self.drift_share_sums[index].T
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(squares > 0, np.maximum(total * total / squares, 1.0), 1.0)

    @property
    def dof(self) -> np.ndarray:
        """(P,) nu of each point's Student-t predictive distribution (module docstring), NaN before its start."""
        return np.where(np.isnan(self.reported).any(axis=(1, 2)), np.nan, tail_dof(self.ratio))

    def _coasting(self, frames: np.ndarray, detour: np.ndarray) -> np.ndarray:
        """C (n, 2, 2) after (n,) ``frames`` steps on the dynamics summing to the (n, 2) ``detour`` disagreement (px^2).

        (t^2 q + |d|^2 / 2) I (module docstring).
        """
        return (frames**2 * self.miss + 0.5 * np.einsum("ni,ni->n", detour, detour))[:, None, None] * np.eye(2)

    def begin_frame(self) -> None:
        """Before a frame's steps: forget part of the pooled and per-point innovation statistics."""
        self._nis *= FORGET
        self._miss *= FORGET
        self._point_nis *= FORGET

    def update(self, index: np.ndarray, predicted: np.ndarray, s_pred: np.ndarray, z: np.ndarray, R: np.ndarray,
               found: np.ndarray, xy: np.ndarray, sigma: np.ndarray, retaken: np.ndarray,
               disagreement: np.ndarray, offset_floor: np.ndarray | None = None,
               jump: np.ndarray | None = None) -> None:
        """The reported covariance of points ``index`` after a step, and the pooled statistics.

        predicted (n, 2), s_pred (n, 2, 2): the gate's prediction and its covariance;
        z (n, 2), R (n, 2, 2) finite: the measurement; found (n,) bool: used (in the gate);
        xy (n, 2), sigma (n, 2, 2): the filter's estimate and covariance after the step;
        retaken (n,) bool: the reference patch was re-taken at the estimate;
        disagreement (n, 2): the local minus the dominant motion's one-step prediction at the point (px);
        offset_floor (n,): the least per-axis variance of a re-taken reference's offset (px^2; the module docstring's
        W, ``ReferenceMatcher.offset_floor``), None or 0: none;
        jump (n, 2): where the match is a re-acquisition's, its move from the prediction (px; ``GatedMeasurement.jump``:
        J, module docstring), None or 0: none.
        """
        S = s_pred + R
        if found.any():
            nu = z[found] - predicted[found]
            nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S[found], nu[..., None])[..., 0])
            self._nis += (nis.sum(), nis.size)
            self._point_nis[index[found]] += np.column_stack([nis, np.ones_like(nis)])
            self._miss += ((nu * nu).sum(), nu.shape[0])
        lam = self.scale
        # Where the patch may be before this frame's match (lambda s_pred holds this frame's one-step miss; the
        # disagreement of the two motions over this frame adds to that of the frames coasted).
        coasting = self._coasting(self.coasted[index], self.detour[index] + disagreement)  # C', px^2
        before = lam * s_pred + coasting
        # The probability that the patch lies in the gate {nu^T S^-1 nu <= gamma} under N(predicted, before),
        # isotropic approximation: 1 - exp(-gamma s_gate / (2 s_before)); a match found when it does not is wrong.
        ratio = np.trace(S, axis1=1, axis2=2) / np.maximum(np.trace(before, axis1=1, axis2=2), 1e-12)
        # Given the innovation: a right match puts nu ~ N(0, F), F the one-step miss of the motion followed, a wrong
        # one anywhere in the gate (area pi gamma sqrt|S|); P(wrong | nu) = expit(log prior odds - log(area N(nu; 0, F))),
        # prior odds w0 / (1 - w0).
        nu = np.where(found[:, None], z - predicted, 0.0)
        followed = max(lam, 1e-6) * S + self._coasting(self.coasted[index], np.zeros_like(nu))  # 1e-6: all nu = 0
        right = np.log(np.pi * self.gamma) + 0.5 * np.log(np.linalg.det(S)) + log_gauss2(nu, 0.0, followed)
        log_prior = -0.5 * self.gamma * ratio  # log w0; log(1 - w0) below, floored where w0 rounds to 1
        log_odds = log_prior - np.log(np.maximum(-np.expm1(log_prior), 1e-300))
        wrong = np.where(found, expit(log_odds - right), 0.0)
        step = xy - predicted
        share = wrong[:, None, None] * (before + np.einsum("ni,nj->nij", step, step))
        self.drift[index] += share
        traces = np.trace(share, axis1=1, axis2=2)
        self.drift_share_sums[index] += np.column_stack([traces, traces * traces])
        # R: a point found again after coasting is where the match is or, if the match is a look-alike, about where
        # its coasting left it: that share's C' is a bounded either-or (part of A), not a tail (module docstring).
        returning = found & (self.coasted[index] > 0)
        self.bounded[index[returning]] += wrong[returning, None, None] * coasting[returning]
        if jump is not None:  # J: the point is where the re-acquisition put it or where it was predicted
            either = np.where(found[:, None, None], np.einsum("ni,nj->nij", jump, jump), 0.0)
            self.drift[index] += either
            self.bounded[index] += either
        scaled = max(lam, 1.0) * sigma
        self.coasted[index] = np.where(found, 0, self.coasted[index] + 1)
        self.detour[index] = np.where(found[:, None], 0.0, self.detour[index] + disagreement)
        coast = self._coasting(self.coasted[index], self.detour[index])
        self._report(index, scaled, self.drift[index], coast)
        self.walk[index[retaken]] += lam * sigma[retaken]  # the new reference's offset, from the next frame on
        if offset_floor is not None:  # a re-take's offset from the first patch: W at least that floor per axis
            lift = np.maximum(offset_floor[:, None] - np.diagonal(self.walk[index], axis1=1, axis2=2), 0.0)  # (n, 2)
            self.walk[index] += lift[:, :, None] * np.eye(2)
