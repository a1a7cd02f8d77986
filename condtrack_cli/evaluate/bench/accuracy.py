"""Accuracy and covariance calibration of every method on every sequence with ground truth; the support table."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from condtrack_cli import registry
from condtrack_cli.evaluate.bench.common import fmt, run_track, sequences
from condtrack_cli.evaluate.groundtruth import load_gt_csv
from condtrack_cli.evaluate.score import score_tracks
from condtrack_cli.io.read import read_tracks


def accuracy_table(max_points: int, work: Path) -> list[str]:
    """Markdown rows: every method on every sequence with ground truth."""
    lines = [
        "| sequence | method | points | <δ_avg | AJ | OA | cov95 | median err (px) | wall (s) | × stk |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, folder, queries, gt_path in sequences(max_points, work):
        truth = load_gt_csv(gt_path)
        stk_seconds = None
        for method in registry.tracking_methods():
            out = work / f"{name.replace('/', '_')}.{method}.h5"
            seconds, _, code, message = run_track([str(folder), "-p", str(queries), "-m", method, "-o", str(out)])
            if code != 0:
                lines.append(f"| {name} | {method} | | failed: {message} | | | | | | |")
                continue
            stk_seconds = seconds if method == "stk" else stk_seconds
            result, data = score_tracks(read_tracks(out)[0], truth, "first")
            ratio = f"{seconds / stk_seconds:.1f}" if stk_seconds else "n/a"
            lines.append(
                f"| {name} | {method} | {len(data.point_id)} | {fmt(result['delta_avg'])} | {fmt(result['AJ'])} | "
                f"{fmt(result['OA'])} | {fmt(result['cov95'])} | {fmt(result['median_err'])} | {seconds:.1f} | {ratio} |"
            )
            print(lines[-1], file=sys.stderr)
    return lines


def calibration_table(max_points: int, work: Path) -> list[str]:
    """Markdown rows: the covariance calibration of every track file ``accuracy_table`` left in ``work``.

    Coverage of the predicted ellipses of level 50/90/95/99 %, the mean NEES (ideal 2) and the
    share of evaluated rows with a finite covariance, for every method whose output has covariances.
    """
    lines = [
        "| sequence | method | cov50 | cov90 | cov95 | cov99 | NEES | finite |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, _, _, gt_path in sequences(max_points, work):
        truth = load_gt_csv(gt_path)
        for method in registry.tracking_methods():
            out = work / f"{name.replace('/', '_')}.{method}.h5"
            if not out.is_file():
                continue
            result, _ = score_tracks(read_tracks(out)[0], truth, "first")
            if result["cov95"] is None:  # no ellipse at all: a method without covariance
                continue
            cells = [fmt(result[key]) for key in ("cov50", "cov90", "cov95", "cov99")]
            nees = "n/a" if result["nees"] is None else f"{result['nees']:.2f}"
            lines.append(f"| {name} | {method} | {' | '.join(cells)} | {nees} | {fmt(result['cov_finite'])} |")
    return lines


#: Bins of the neighbourhood support for ``support_table``.
SUPPORT_BINS = (0.0, 0.4, 0.6, 0.8, 1.0001)


def support_table(folder: Path, window: int = 32) -> list[str]:
    """Markdown rows: the dominant model's one-step prediction error on a sequence's GT, by support.

    For every GT track seen on frames k-1 and k, the error |x_k - (x_{k-1} +
    U(x_{k-1}))| of the default global fit, binned by the mean robust weight
    over the ``window`` square around x_{k-1} (``neighbourhood_support``): the
    measurement behind ``auto``'s thresholds and the misfit term of Q_k. Then
    the one-step error of each motion: the ``robust`` stage's global fit and
    local field (with and without its block-matching start) and the ``dis``
    stage's (the default) at their default settings.
    """
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.motion.dense import DisMotionSettings, make_dis_motion
    from condtrack_cli.motion.local import LocalMotion
    from condtrack_cli.motion.model import displacement
    from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings
    from condtrack_cli.motion.state_noise import neighbourhood_support
    from condtrack_cli.types import Frame

    truth = load_gt_csv(folder / "tracks.csv")
    settings = RobustMotionSettings()
    motion = GlobalMotion(settings)
    fields = {"local field (robust)": LocalMotion(settings),
              "local field (robust), no search (local_search 0)": LocalMotion(settings.model_copy(update={"local_search": 0}))}
    dis = make_dis_motion(DisMotionSettings())
    support, prev = [], None
    error = {"dominant model (robust)": [], **{name: [] for name in fields}, "dominant model (dis)": [], "DIS field (dis)": []}
    for index, image in enumerate(open_frames(FrameSettings(), folder)):
        frame = Frame(index, image)
        if prev is not None:
            both = truth.known[:, index - 1] & truth.known[:, index]
            x, x_next = truth.gt_xy[both, index - 1], truth.gt_xy[both, index]
            fit = motion.fit(prev, frame)
            support.append(neighbourhood_support(fit, x, window))
            error["dominant model (robust)"].append(np.linalg.norm(x + displacement(fit, x) - x_next, axis=1))
            for name, local in fields.items():
                error[name].append(np.linalg.norm(x + local.field(prev, frame, fit).displacement(x) - x_next, axis=1))
            dis_fit = dis.global_motion.fit(prev, frame)
            error["dominant model (dis)"].append(np.linalg.norm(x + displacement(dis_fit, x) - x_next, axis=1))
            dis_field = dis.local_motion.field(prev, frame, dis_fit)
            error["DIS field (dis)"].append(np.linalg.norm(x + dis_field.displacement(x) - x_next, axis=1))
        prev = frame
    support = np.concatenate(support)
    error = {name: np.concatenate(values) for name, values in error.items()}
    dominant = error["dominant model (robust)"]
    lines = [f"One-step error of the dominant model (robust) on {folder.name}, by support:", "",
             "| support | share | median error (px) |", "|---|---|---|"]
    for low, high in zip(SUPPORT_BINS[:-1], SUPPORT_BINS[1:]):
        inside = (support >= low) & (support < high)
        median = f"{np.median(dominant[inside]):.2f}" if inside.any() else "n/a"
        lines.append(f"| [{low:.1f}, {min(high, 1.0):.1f}{']' if high > 1 else ')'} | {inside.mean():.2f} | {median} |")
    lines += ["", f"One-step error of each motion on {folder.name} ({len(dominant)} GT steps):", "",
              "| motion | median (px) | within 1 px | over 16 px |", "|---|---|---|---|"]
    for name, values in error.items():
        lines.append(f"| {name} | {np.median(values):.2f} | {np.mean(values < 1):.2f} | {np.mean(values > 16):.2f} |")
    return lines
