"""Contract of a ``measure`` stage: a frame and reference patches in, each point's measurement z_k, R_k out (§5.2).

A measure stage is registered with ``register("measure", name, SettingsModel)`` on a
factory called ``factory(settings) -> Measurer``. The filters keep the reference
patches (``filters/reference.py``) and ask the measurer to take, compare and
match them. Images are (H, W) float32 grey levels (``Frame.gray``); positions px
in the package's pixel convention; covariances px^2.
The built-in stages are rows of ``registry.BUILTINS`` instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from condtrack_cli.errors import CondtrackError


@dataclass(frozen=True)
class Measurement:
    """The measurements of P points on one frame.

    z: (P, 2) float64 measured position (px, sub-pixel); NaN where no candidate was in the gate.
    R: (P, 2, 2) float64 covariance of z (px^2, eq. 9); diagonal +inf (off-diagonal 0) where the
       surface carries no information (and where z is NaN); otherwise symmetric with eigenvalues
       >= ``r_floor``.
    residual: (P,) float64 r_k(z_k), the SSD at the integer minimum (grey levels^2); NaN with z.
    aligned: (P,) float64 or None, the matching cost at the sub-pixel z_k (bilinear; at most ``residual``), which
       a texture's misalignment by a fraction of a pixel does not inflate; None: ``residual`` stands for it.
    informative: (P,) bool, R finite.
    """

    z: np.ndarray
    R: np.ndarray
    residual: np.ndarray
    informative: np.ndarray
    aligned: np.ndarray | None = None


class Measurer(Protocol):
    """Reference patches and their match in the validation gate."""

    template_side: int  #: side t (px, odd) of the patches ``templates`` returns

    def noise_sigma(self, gray: np.ndarray) -> float:
        """The acquisition noise std of the frame (grey levels)."""

    def templates(self, gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """(M, t, t) float32 patches centred on (M, 2) positions ``xy`` (px)."""

    def cost(self, templates: np.ndarray, patches: np.ndarray) -> np.ndarray:
        """(M,) matching cost of aligned (M, t, t) patch pairs (grey levels^2)."""

    # Optional: ``searched(predicted (P, 2), gate_cov (P, 2, 2), xy (P, 2)) -> (P,) bool``, whether the search of
    # :meth:`measure` around ``predicted`` held the candidate nearest to ``xy`` (the filters' Lucas-Kanade fallback,
    # ``filters/reference.py``, re-measures only around centres outside it; without it: the gate ellipse).
    # Optional: ``least_residuals(gray, templates (P, t, t), predicted (P, 2), gate_cov (P, 2, 2)) -> (P,)``, the
    # ``Measurement.residual`` :meth:`measure` would report, alone (the re-acquisition measures further only the
    # points whose match could be used; without it: every point).
    # Optional: ``pixel_count: float``, the pixel count n of ``cost``'s noise: under a right match and acquisition
    # noise sigma a cost is about n 2 sigma^2 (without it: t^2, a plain sum over the patch; the ``ssd`` stage's
    # weighted costs have sum w, the weights scaled so that sum w = sum w^2).
    # Optional: ``resized(side) -> Measurer``, the same stage with patches of odd ``side`` px (the drift check
    # matches each point's first patch at ``filter.clf/cnlf.drift_check_template``; without it: at ``template_side``).

    def measure(self, gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray, gate_cov: np.ndarray,
                sigma: float) -> Measurement:
        """Match (P, t, t) ``templates`` around (P, 2) ``predicted`` positions within the gate of
        innovation covariance (P, 2, 2) ``gate_cov`` (px^2), with noise std ``sigma`` (grey levels)."""


class CheckedMeasurer:
    """A measure stage from outside condtrack (a plugin), its outputs checked against this contract.

    Each call's arrays must have the shapes above (P the points asked); R no NaN and no negative variance. Otherwise a
    CondtrackError names the stage, where a numpy traceback deep in a filter would come. Every other attribute (the
    optional ones included: ``hasattr`` answers as for the stage itself) is the stage's own.
    """

    def __init__(self, measurer: Measurer, name: str):
        self._measurer, self._name = measurer, name

    def __getattr__(self, attribute: str):
        found = getattr(self._measurer, attribute)
        if attribute == "resized":  # optional: the same stage with other patches, checked as well
            return lambda side: CheckedMeasurer(found(side), self._name)
        return found

    def _refuse(self, what: str, got: object, expected: str) -> None:
        shape = f"shape {got.shape}" if isinstance(got, np.ndarray) else f"a {type(got).__name__}"
        raise CondtrackError(f"measure stage '{self._name}' returned {what} of {shape}; expected {expected} "
                             "(measure/interface.py)")

    def _check(self, what: str, got: object, shape: tuple[int, ...]) -> None:
        if not isinstance(got, np.ndarray) or got.shape != shape or got.dtype.kind not in "biuf":
            self._refuse(what, got, f"{shape} numbers")

    def templates(self, gray: np.ndarray, xy: np.ndarray) -> np.ndarray:
        t = self._measurer.templates(gray, xy)
        side = self._measurer.template_side
        self._check("templates", t, (len(xy), side, side))
        return t

    def cost(self, templates: np.ndarray, patches: np.ndarray) -> np.ndarray:
        c = self._measurer.cost(templates, patches)
        self._check("cost", c, (len(templates),))
        return c

    def measure(self, gray: np.ndarray, templates: np.ndarray, predicted: np.ndarray, gate_cov: np.ndarray,
                sigma: float) -> Measurement:
        m = self._measurer.measure(gray, templates, predicted, gate_cov, sigma)
        p = len(predicted)
        if not isinstance(m, Measurement):
            self._refuse("measure", m, "a Measurement")
        for what, got, shape in (("z", m.z, (p, 2)), ("R", m.R, (p, 2, 2)), ("residual", m.residual, (p,)),
                                 ("informative", m.informative, (p,))) + (
                                     (("aligned", m.aligned, (p,)),) if m.aligned is not None else ()):
            self._check(what, got, shape)
        if np.isnan(m.R).any() or (m.R[:, [0, 1], [0, 1]] < 0).any():
            raise CondtrackError(f"measure stage '{self._name}' returned an R with a NaN or a negative variance; "
                                 "expected covariances (px^2, measure/interface.py)")
        return m
