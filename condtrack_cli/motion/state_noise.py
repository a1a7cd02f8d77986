"""Q_k of eq. (1) from the global fit, and the neighbourhood support it reads (the robust weights around a point)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from condtrack_cli.motion.model import MotionFit, motion_basis


def neighbourhood_support(fit: MotionFit, xy: np.ndarray, window: int) -> np.ndarray:
    """(N,) mean robust weight of the dominant-motion fit over a ``window`` x ``window`` square at each of (N, 2) xy.

    Near 1 where the neighbourhood follows the dominant motion, near 0 where it
    does not (another object, parallax, an occluder). Positions are rounded to
    the nearest pixel and clamped to the frame.
    """
    mean = cv2.boxFilter(fit.weights, -1, (window, window), borderType=cv2.BORDER_REFLECT)
    h, w = mean.shape
    cols = np.clip(np.rint(xy[:, 0]), 0, w - 1).astype(int)
    rows = np.clip(np.rint(xy[:, 1]), 0, h - 1).astype(int)
    return mean[rows, cols].astype(np.float64)


def state_noise(
    fit: MotionFit, xy: np.ndarray, q_floor: float, q_misfit: float = 0.0, misfit_window: int = 15,
    support: np.ndarray | None = None,
) -> np.ndarray:
    """Q_k at (N, 2) positions: (N, 2, 2) px^2.

    Q_k = P(x) Sigma_theta P(x)^T + (q_floor + q_misfit (1 - w(x))^2) I, with
    w(x) the mean robust weight around x (``neighbourhood_support``), or the (N,)
    ``support`` given instead (a covered point's, read where it was last seen: ``CLFTracker``).

    The paper only says Q_k is estimated from the images. Our choice has three
    parts: the uncertainty of the fitted motion propagated to the point; a floor
    for what any parametric model leaves out; and a model-misfit term read off
    the robust fit itself: where the neighbourhood of x was rejected as outliers
    the dominant motion says little about x, so the point may move by up to a
    few pixels more (``python -m condtrack_cli.evaluate.bench --support SEQUENCE``
    on the real sequences of ../shared/data: one-step prediction error median
    about 10 px where the support is below 0.4, 0.45-1.1 px where it is >= 0.8).
    The weighted-least-squares Sigma_theta treats pixels as independent, so it is
    tiny on textured frames; it grows where the fit is poorly constrained.
    """
    basis = motion_basis(fit.model, xy, fit.origin, fit.length)
    if q_misfit and support is None:
        support = neighbourhood_support(fit, xy, misfit_window)
    isotropic = q_floor + (q_misfit * (1 - support) ** 2 if q_misfit else 0.0)
    return basis @ fit.theta_cov @ basis.transpose(0, 2, 1) + np.multiply.outer(isotropic, np.eye(2))


@dataclass(frozen=True)
class StateNoise:
    """The parameters of :func:`state_noise` (``motion.q_floor``, ``q_misfit``, ``misfit_window``), for the filters."""

    q_floor: float  #: px^2
    q_misfit: float  #: px^2
    misfit_window: int  #: px

    @classmethod
    def of(cls, settings) -> "StateNoise":
        """The parameters of a motion stage's settings (any model with ``q_floor``, ``q_misfit``, ``misfit_window``)."""
        return cls(settings.q_floor, settings.q_misfit, settings.misfit_window)

    def at(self, fit: MotionFit, xy: np.ndarray, support: np.ndarray | None = None) -> np.ndarray:
        """Q_k (N, 2, 2) px^2 of the dynamics of ``fit`` at (N, 2) positions xy (px); support (N,): the
        neighbourhood support to use instead of the one read around xy (:func:`state_noise`)."""
        return state_noise(fit, xy, self.q_floor, self.q_misfit, self.misfit_window, support)

    def support(self, fit: MotionFit, xy: np.ndarray) -> np.ndarray:
        """(N,) the mean robust weight of ``fit`` around (N, 2) positions xy that Q_k reads (``neighbourhood_support``)."""
        return neighbourhood_support(fit, xy, self.misfit_window)
