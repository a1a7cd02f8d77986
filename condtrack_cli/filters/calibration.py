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

The model, per point, reported covariance = max(lambda, 1) Sigma + D + C:

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
  query. Each re-take of the reference at the posterior adds lambda Sigma_post.
  Each match adds the spread of a wrong match with its probability (PDA-like,
  one candidate): with B = lambda Sigma_{k|k-1} + C' the covariance of where the
  patch may be, the patch lies in the gate {nu^T S^-1 nu <= gamma} with
  probability about 1 - exp(-gamma tr S / (2 tr B)) (isotropic approximation);
  a match found when it does not is on something else, so D gains
  exp(-gamma tr S / (2 tr B)) (B + s s^T), s the step the update made. C' is C
  (below) with d including this frame's disagreement (lambda Sigma_{k|k-1}
  already holds this frame's one-step miss): a point found on every frame may
  still have followed either motion over this one, so where the local and the
  dominant motion part by much more than the gate, a match in the gate may be
  on the patch the other motion carried there. This keeps a point re-found
  after coasting (large C, the usual gate), or matched on every frame where the
  two motions disagree (parallax, a moving object's edge), from reporting a
  small covariance around a wrong patch: on the shared real sets the found rows
  outside their 99 % ellipse were mostly on such disagreement (issue 12).
- C: the coasting excess, 0 on a found frame. While a point is not found for t
  frames its error grows by the dynamics' one-step miss every frame, in the same
  direction (a constant velocity error): t^2 q I, q the per-axis mean squared
  innovation |nu|^2 / 2 of the found points (pooled as lambda); plus d d^T / 2,
  d the sum over the frames coasted of the local minus the dominant motion's
  prediction at the point: the second moment of the equal-weight mixture of the
  two dynamics about the one followed (a covered point's window moves with its
  occluder; a point on parallax may follow either).

The filter's own state (its covariance, gate and gain) is unchanged, so positions
are those of the filter without the model, bit for bit; ``filter.smooth`` smooths
the filter's own covariance and adds back each frame's excess
(``smoother.error_excess``).
"""

from __future__ import annotations

import numpy as np

#: Weight kept by the pooled innovation statistics from one frame to the next.
FORGET = 0.5


class ErrorModel:
    """Per-point terms of the reported covariance of P points (module docstring); arrays (P, ...)."""

    def __init__(self, n_points: int, gamma: float):
        self.gamma = gamma  #: the gate's chi-square threshold
        self.drift = np.zeros((n_points, 2, 2))  #: D, px^2
        self.coasted = np.zeros(n_points)  #: t, frames since the point was last found
        self.detour = np.zeros((n_points, 2))  #: sum over the frames coasted of the dynamics' disagreement, px
        self.reported = np.full((n_points, 2, 2), np.nan)  #: the covariance reported, px^2
        self._nis = np.zeros(2)  #: forgotten sums of NIS and of the count of found points
        self._miss = np.zeros(2)  #: forgotten sums of |nu|^2 and of the count

    @property
    def scale(self) -> float:
        """lambda: pooled mean NIS / 2 (1 before any point was found)."""
        return self._nis[0] / (2.0 * self._nis[1]) if self._nis[1] > 0 else 1.0

    @property
    def miss(self) -> float:
        """q: pooled per-axis mean squared innovation (px^2; 0 before any point was found)."""
        return self._miss[0] / (2.0 * self._miss[1]) if self._miss[1] > 0 else 0.0

    def start(self, index: np.ndarray, sigma: np.ndarray) -> None:
        """Points ``index`` start with covariance (n, 2, 2) ``sigma``, no drift, not coasting."""
        self.drift[index] = 0.0
        self.coasted[index] = 0
        self.detour[index] = 0.0
        self.reported[index] = sigma

    def _coasting(self, frames: np.ndarray, detour: np.ndarray) -> np.ndarray:
        """C (n, 2, 2) after (n,) ``frames`` steps on the dynamics summing to the (n, 2) ``detour`` disagreement (px^2).

        t^2 q I + d d^T / 2 (module docstring).
        """
        return (frames**2 * self.miss)[:, None, None] * np.eye(2) + 0.5 * np.einsum("ni,nj->nij", detour, detour)

    def begin_frame(self) -> None:
        """Before a frame's steps: forget part of the pooled innovation statistics."""
        self._nis *= FORGET
        self._miss *= FORGET

    def update(self, index: np.ndarray, predicted: np.ndarray, s_pred: np.ndarray, z: np.ndarray, R: np.ndarray,
               found: np.ndarray, xy: np.ndarray, sigma: np.ndarray, retaken: np.ndarray,
               disagreement: np.ndarray) -> None:
        """The reported covariance of points ``index`` after a step, and the pooled statistics.

        predicted (n, 2), s_pred (n, 2, 2): the gate's prediction and its covariance;
        z (n, 2), R (n, 2, 2) finite: the measurement; found (n,) bool: used (in the gate);
        xy (n, 2), sigma (n, 2, 2): the filter's estimate and covariance after the step;
        retaken (n,) bool: the reference patch was re-taken at the estimate;
        disagreement (n, 2): the local minus the dominant motion's one-step prediction at the point (px).
        """
        S = s_pred + R
        if found.any():
            nu = z[found] - predicted[found]
            nis = np.einsum("ni,ni->n", nu, np.linalg.solve(S[found], nu[..., None])[..., 0])
            self._nis += (nis.sum(), nis.size)
            self._miss += ((nu * nu).sum(), nu.shape[0])
        lam = self.scale
        # Where the patch may be before this frame's match (lambda s_pred holds this frame's one-step miss; the
        # disagreement of the two motions over this frame adds to that of the frames coasted).
        before = lam * s_pred + self._coasting(self.coasted[index], self.detour[index] + disagreement)
        # The probability that the patch lies in the gate {nu^T S^-1 nu <= gamma} under N(predicted, before),
        # isotropic approximation: 1 - exp(-gamma s_gate / (2 s_before)); a match found when it does not is wrong.
        ratio = np.trace(S, axis1=1, axis2=2) / np.maximum(np.trace(before, axis1=1, axis2=2), 1e-12)
        wrong = np.where(found, np.exp(-0.5 * self.gamma * ratio), 0.0)
        step = xy - predicted
        self.drift[index] += wrong[:, None, None] * (before + np.einsum("ni,nj->nij", step, step))
        scaled = max(lam, 1.0) * sigma
        self.coasted[index] = np.where(found, 0, self.coasted[index] + 1)
        self.detour[index] = np.where(found[:, None], 0.0, self.detour[index] + disagreement)
        self.reported[index] = scaled + self.drift[index] + self._coasting(self.coasted[index], self.detour[index])
        self.drift[index[retaken]] += lam * sigma[retaken]  # the new reference's offset, from the next frame on
