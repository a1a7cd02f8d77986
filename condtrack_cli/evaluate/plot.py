"""``condtrack eval --plot``: a reliability diagram and a histogram of the normalised errors (matplotlib, optional).

The reliability diagram plots, for every level p in (0, 1), the share of evaluated
rows whose ground truth lies in the predicted ellipse of level p against p: a
calibrated distribution follows the diagonal, an overconfident one lies below it.
Two curves: under each row's Student-t (``dof``) and with every row read as a
Gaussian of the same covariance.
The histogram is that of the Mahalanobis distance sqrt(d^T C^-1 d) of the errors
with a finite covariance, against its law for a calibrated 2-D Gaussian error
(Rayleigh, density r exp(-r^2 / 2)).
"""

from __future__ import annotations

import numpy as np

from condtrack_cli.errors import CondtrackError, warn
from condtrack_cli.evaluate.groundtruth import Aligned
from condtrack_cli.evaluate.metrics import COVERAGE_LEVELS, normalised_error, scored_frames
from condtrack_cli.predictive import ellipse_level
from condtrack_cli.io.atomic import atomic_path

#: Levels of the reliability curve.
CURVE_LEVELS = np.linspace(0.01, 0.99, 99)

#: Largest Mahalanobis distance on the histogram's axis (larger ones pile up in the last bin).
HISTOGRAM_MAX = 8.0


def reliability_curve(data: Aligned, mode: str, gaussian: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """(levels (L,), observed coverage (L,), counted rows) over the GT-visible scored rows with an ellipse.

    Under each row's Student-t, or (``gaussian``) with every row read as a Gaussian.
    """
    rows = scored_frames(data.query_frame, data.gt_visible.shape[1], mode) & data.gt_known & data.gt_visible
    unbounded, bounded, m2 = normalised_error(data.pred_xy - data.gt_xy, data.pred_cov)
    unbounded, bounded = unbounded & rows, bounded & rows
    counted = int((unbounded | bounded).sum())
    dof = np.inf if gaussian else np.where(np.isnan(data.pred_dof), np.inf, data.pred_dof)[bounded]
    levels = np.sort(ellipse_level(m2[bounded], dof))
    inside = np.searchsorted(levels, CURVE_LEVELS, side="right") + unbounded.sum()
    return CURVE_LEVELS, inside / max(counted, 1), counted


def write_plot(data: Aligned, mode: str, path: str, title: str) -> None:
    """Write the reliability diagram and the histogram side by side to the PNG ``path``.

    Nothing to plot (the predictions hold no covariance, as STK's, or no scored row has an ellipse): a
    CondtrackWarning saying so and no file. CondtrackError when matplotlib is missing.
    """
    if np.isnan(data.pred_cov).all():
        warn("--plot: the predictions hold no covariance: nothing to plot")
        return
    levels, observed, counted = reliability_curve(data, mode)
    if counted == 0:
        warn("--plot: no GT-visible scored row has a predicted ellipse: nothing to plot")
        return
    _, observed_gauss, _ = reliability_curve(data, mode, gaussian=True)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise CondtrackError("--plot needs matplotlib: pip install 'condtrack[plot]'") from None
    rows = scored_frames(data.query_frame, data.gt_visible.shape[1], mode) & data.gt_known & data.gt_visible
    _, bounded, m2 = normalised_error(data.pred_xy - data.gt_xy, data.pred_cov)
    distance = np.minimum(np.sqrt(m2[bounded & rows]), HISTOGRAM_MAX)

    figure, (left, right) = plt.subplots(1, 2, figsize=(8, 3.6), dpi=80)
    left.plot([0, 1], [0, 1], color="0.6", linestyle="--", label="calibrated")
    left.plot(levels, observed, color="C0", label=f"Student-t per row ({counted} rows)")
    left.plot(levels, observed_gauss, color="C2", label="read as Gaussian")
    marks = np.array(COVERAGE_LEVELS)
    left.plot(marks, np.interp(marks, levels, observed), "o", color="C0")
    left.plot(marks, np.interp(marks, levels, observed_gauss), "o", color="C2")
    left.set(xlim=(0, 1), ylim=(0, 1), xlabel="ellipse level p", ylabel="share of truth inside", title="reliability")
    left.legend(loc="upper left", fontsize="small")
    bins = np.linspace(0, HISTOGRAM_MAX, 33)
    right.hist(distance, bins=bins, density=True, color="C1", alpha=0.7, label=f"finite covariance ({distance.size} rows)")
    r = np.linspace(0, HISTOGRAM_MAX, 200)
    right.plot(r, r * np.exp(-r * r / 2), color="0.3", label="calibrated (Rayleigh)")
    right.set(xlabel=f"Mahalanobis distance of the error (last bin: >= {HISTOGRAM_MAX:g})", ylabel="density",
              title="normalised error")
    right.legend(loc="upper right", fontsize="small")
    figure.suptitle(title, fontsize="small")
    figure.tight_layout()
    try:
        with atomic_path(path) as temporary:
            figure.savefig(temporary, format="png")
    finally:
        plt.close(figure)
