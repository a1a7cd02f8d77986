"""The section against OpenCV LK maxLevel 3 (issue 11): real sets and synthetic scenes, with the done-when checks.

The same track files also give the coverage of each method's reported covariance (issue 12), with its targets.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from condtrack_cli.evaluate.bench.common import REPO, fmt, gt_queries, run_track, write_queries
from condtrack_cli.evaluate.groundtruth import GroundTruth, load_gt_csv
from condtrack_cli.evaluate.score import score_tracks
from condtrack_cli.io.read import read_tracks


#: Methods of the real-video table, after the OpenCV LK baseline.
VERSUS_LK_METHODS = ("auto", "clf", "cnlf", "stk")

#: Methods whose rows carry a covariance: the coverage table of issues 12 and 27.
COVARIANCE_METHODS = ("auto", "clf", "cnlf")

#: The ``paper`` preset (issue 29): the method as published, run with each of these methods beside the
#: defaults; its columns are named "paper <method>". Its CNLF regresses the motion per particle: slow.
PAPER_CONFIG = REPO / "configs" / "paper.yaml"
PAPER_METHODS = ("clf", "cnlf", "auto")

#: Issue 27's calibration targets: (metric key, lowest, highest) share of the truth inside the ellipse of each row's
#: Student-t distribution, and the share of rows with a finite covariance.
COVERAGE_TARGETS = (("cov50", 0.42, 0.62), ("cov90", 0.85, 0.95), ("cov95", 0.90, 0.98), ("cov99", 0.97, 1.0),
                    ("cov_finite", 0.95, 1.0))

#: Synthetic scenes of ``condtrack synth`` scored against LK, each at its defaults (seed 0).
VERSUS_LK_SCENES = ("camera_motion", "occlusion", "ring", "illumination", "fast")


def versus_lk_queries(truth: GroundTruth, oxford: bool, max_points: int = 300) -> np.ndarray:
    """Issue 11's real-video queries: first observation of tracks with >= 5 observations (>= 2 on Oxford sets)."""
    return gt_queries(truth, min_observations=2 if oxford else 5, max_points=max_points)


def paper_columns(paper: tuple[str, ...]) -> tuple[str, ...]:
    """The columns of the ``paper`` preset run with each method of ``paper``."""
    return tuple(f"paper {method}" for method in paper)


def score_versus_lk(folder: Path, queries: Path, truth: GroundTruth, work: Path, stem: str,
                    extra: tuple[str, ...] = (), paper: tuple[str, ...] = PAPER_METHODS) -> dict:
    """{column: (metrics dict, wall seconds)} for OpenCV LK, ``VERSUS_LK_METHODS`` and the ``paper`` preset
    with each method of ``paper`` (column "paper <method>", ``-c configs/paper.yaml``) on one sequence.

    LK runs in this process (frame reading and both LK directions timed); each
    condtrack method runs as its own ``condtrack track`` process (whole-process
    wall time, start-up included), with the ``extra`` arguments (e.g. ``--set`` overrides).
    A failed method maps to (None, message).
    """
    from condtrack_cli.evaluate.opencv_lk import opencv_lk
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.queries import read_queries

    started = time.perf_counter()
    lk = opencv_lk(folder, read_queries(queries, open_frames(FrameSettings(), folder).info))
    results = {"lk": (score_tracks(lk, truth, "first")[0], time.perf_counter() - started)}
    for method in VERSUS_LK_METHODS:
        out = work / f"{stem}.{method}.h5"
        seconds, _, code, message = run_track([str(folder), "-p", str(queries), "-m", method, "-o", str(out), *extra])
        results[method] = (None, message) if code else (score_tracks(read_tracks(out)[0], truth, "first")[0], seconds)
    for method, column in zip(paper, paper_columns(paper)):
        out = work / f"{stem}.paper-{method}.h5"
        seconds, _, code, message = run_track([str(folder), "-p", str(queries), "-c", str(PAPER_CONFIG), "-m", method,
                                               "-o", str(out), *extra])
        results[column] = (None, message) if code else (score_tracks(read_tracks(out)[0], truth, "first")[0], seconds)
    return results


def _cell(result: tuple) -> str:
    metrics, seconds = result
    return f"failed: {seconds}" if metrics is None else f"{fmt(metrics['delta_avg'])} ({seconds:.0f} s)"


def _delta(results: dict, column: str) -> float:
    metrics = results[column][0]
    return np.nan if metrics is None or metrics["delta_avg"] is None else metrics["delta_avg"]


def _check(ok: bool, text: str) -> str:
    return f"- [{'x' if ok else ' '}] {'pass' if ok else 'FAIL'}: {text}"


def real_video_table(work: Path, shared: Path, max_points: int = 300, extra: tuple[str, ...] = (),
                     paper: tuple[str, ...] = PAPER_METHODS) -> list[str]:
    """Markdown: <δ_avg of OpenCV LK, each method and the paper preset's per real set of ``shared``, then issue
    11's done-when checks."""
    columns = ("lk",) + VERSUS_LK_METHODS + paper_columns(paper)
    lines = ["| set | points | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    per_set = {}
    for folder in sorted(shared.glob("*/")) if shared.is_dir() else []:
        if not (folder / "tracks.csv").is_file():
            continue
        truth = load_gt_csv(folder / "tracks.csv")
        rows = versus_lk_queries(truth, folder.name.startswith("oxford"), max_points)
        queries = work / f"lk11_{folder.name}.queries.csv"
        write_queries(rows, queries)
        per_set[folder.name] = score_versus_lk(folder, queries, truth, work, f"lk11_{folder.name}", extra, paper)
        lines.append(f"| {folder.name} | {len(rows)} | " + " | ".join(_cell(per_set[folder.name][c]) for c in columns) + " |")
        print(lines[-1], file=sys.stderr)
    if not per_set:
        return [f"{shared} is absent: no real-video table."]
    kitti = [name for name in per_set if name.startswith("kt3dmoseg")]
    mean = {c: float(np.mean([_delta(per_set[n], c) for n in kitti])) for c in columns}
    lines.append("| KITTI mean | | " + " | ".join(f"{mean[c]:.3f}" for c in columns) + " |")
    checks = [_check(mean["auto"] >= mean["lk"] + 0.07,
                     f"KITTI mean of auto {mean['auto']:.3f} >= LK mean {mean['lk']:.3f} + 0.07")]
    for name in ("oxford_dinosaur", "oxford_merton1"):
        if name in per_set:
            auto, lk = _delta(per_set[name], "auto"), _delta(per_set[name], "lk")
            checks.append(_check(auto >= lk, f"{name}: auto {auto:.3f} >= LK {lk:.3f}"))
    checks += _better_filter_checks(per_set)
    for name in kitti + [n for n in ("oxford_dinosaur",) if n in per_set]:
        clf, lk = _delta(per_set[name], "clf"), _delta(per_set[name], "lk")
        checks.append(_check(clf >= lk, f"{name}: clf {clf:.3f} >= LK {lk:.3f}"))
    return lines + ["", "Done-when checks of issue 11 (real video):", ""] + checks + [
        "", "Coverage of each row's predictive distribution on the same runs (issues 12 and 27; `condtrack eval` keys):", ""
    ] + coverage_table(per_set, "set", paper)


def _better_filter_checks(per_set: dict) -> list[str]:
    """One check per set: auto within 0.01 of the better of clf and cnlf."""
    checks = []
    for name, results in per_set.items():
        auto, best = _delta(results, "auto"), max(_delta(results, "clf"), _delta(results, "cnlf"))
        checks.append(_check(auto >= best - 0.01, f"{name}: auto {auto:.3f} >= better filter {best:.3f} - 0.01"))
    return checks


def coverage_table(per_set: dict, label: str, paper: tuple[str, ...] = ()) -> list[str]:
    """Markdown: coverage under each row's Student-t and read as Gaussian, finite share, NEES and cov50_rescaled of
    ``COVARIANCE_METHODS`` (and the paper preset's columns of ``paper``) per set, then issue 27's targets (checked on
    ``COVARIANCE_METHODS`` only).

    per_set: {set: {method: (metrics dict, seconds)}} as ``score_versus_lk`` returns; label: the first column's name.
    """
    keys = ("cov50", "cov90", "cov95", "cov99", "cov50_gauss", "cov90_gauss", "cov95_gauss", "cov99_gauss",
            "cov_finite", "nees", "cov50_rescaled")
    lines = [f"| {label} | method | " + " | ".join(keys) + " |", "|---|---|" + "---|" * len(keys)]
    misses = {key: [] for key, _, _ in COVERAGE_TARGETS}
    runs = 0
    for name, results in per_set.items():
        for method in COVARIANCE_METHODS + paper_columns(paper):
            metrics = results[method][0]
            if metrics is None:
                lines.append(f"| {name} | {method} | failed |")
                continue
            lines.append(f"| {name} | {method} | " + " | ".join(fmt(metrics[key]) for key in keys) + " |")
            if method not in COVARIANCE_METHODS:
                continue
            runs += 1
            for key, low, high in COVERAGE_TARGETS:
                if metrics[key] is None or not low <= metrics[key] <= high:
                    misses[key].append(f"{name} {method} {fmt(metrics[key])}")
    checks = [_check(not misses[key], f"{key} in [{low:.2f}, {high:.2f}] on {runs - len(misses[key])} of {runs} runs"
                     + (f"; not on: {', '.join(misses[key])}" if misses[key] else ""))
              for key, low, high in COVERAGE_TARGETS]
    return lines + ["", f"Calibration targets of issue 27, under each row's Student-t ({label}s):", ""] + checks


def synthetic_versus_lk_table(work: Path, extra: tuple[str, ...] = (), paper: tuple[str, ...] = PAPER_METHODS) -> list[str]:
    """Markdown: the ``condtrack synth`` scenes at their defaults, LK, each method and the paper preset's, then
    issue 11's checks."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    columns = ("lk",) + VERSUS_LK_METHODS + paper_columns(paper)
    lines = ["| scene | points | " + " | ".join(f"{c} <δ / AJ / OA" for c in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    per_scene = {}
    for scene in VERSUS_LK_SCENES:
        folder = write_scene(make_scene(scene), work / f"synth_{scene}")
        truth = load_gt_csv(folder / "tracks.csv")
        per_scene[scene] = score_versus_lk(folder, folder / "queries.csv", truth, work, f"synth_{scene}", extra, paper)
        cells = [
            "failed" if m is None else " / ".join(fmt(m[key]) for key in ("delta_avg", "AJ", "OA"))
            for m, _ in (per_scene[scene][c] for c in columns)
        ]
        lines.append(f"| {scene} | {len(truth.point_id)} | " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr)

    def mean(column: str, key: str) -> float:
        values = [per_scene[s][column][0] for s in per_scene]
        return float(np.mean([np.nan if m is None or m[key] is None else m[key] for m in values]))

    means = {key: mean("auto", key) for key in ("delta_avg", "AJ", "OA")}
    checks = [
        _check(means["delta_avg"] >= 0.88, f"auto mean <δ_avg {means['delta_avg']:.3f} >= 0.88"),
        _check(means["AJ"] >= 0.75, f"auto mean AJ {means['AJ']:.3f} >= 0.75"),
        _check(means["OA"] >= 0.90, f"auto mean OA {means['OA']:.3f} >= 0.90"),
    ]
    for scene, results in per_scene.items():
        auto, lk = _delta(results, "auto"), _delta(results, "lk")
        checks.append(_check(auto >= lk, f"{scene}: auto {auto:.3f} >= LK {lk:.3f}"))
    checks += _better_filter_checks(per_scene)
    return lines + ["", "Done-when checks of issue 11 (synthetic scenes):", ""] + checks + [
        "", "Coverage of each row's predictive distribution on the same runs (issues 12 and 27; `condtrack eval` keys):", ""
    ] + coverage_table(per_scene, "scene", paper)


def versus_lk_section(work: Path, shared: Path = REPO.parent / "shared" / "data", extra: tuple[str, ...] = (),
                      paper: tuple[str, ...] = PAPER_METHODS, max_points: int = 300, synthetic: bool = True) -> list[str]:
    """The results.md section of issue 11: real video and synthetic scenes against OpenCV LK maxLevel 3.

    extra: arguments added to every ``condtrack track`` (``--set`` overrides, to measure a variant).
    paper: the methods run with the ``paper`` preset as extra columns (issue 29). max_points: most queries
    per real set. synthetic: also the synthetic scenes' table.
    """
    return [
        "## Against OpenCV LK (issue 11)",
        "",
        "OpenCV LK: `calcOpticalFlowPyrLK` winSize 21, maxLevel 3, forward-backward check 1 px "
        "(`condtrack_cli/evaluate/opencv_lk.py`), run and timed in this process; the methods' times are whole "
        "`condtrack track` processes. Real sets: queries = first observation of tracks with >= 5 observations "
        f"(>= 2 on the Oxford sets), at most {max_points} per set taken evenly; <δ_avg in the 'first' query mode; "
        f"cells are <δ_avg (wall seconds). Track files: bench/out/lk11_<set>.<method>.h5. Columns 'paper <method>': "
        "`condtrack track -c configs/paper.yaml -m <method>`, the method as published (issue 29; "
        "bench/out/lk11_<set>.paper-<method>.h5).",
        "",
    ] + real_video_table(work, shared, max_points, extra, paper) + ([
        "",
        "Synthetic scenes of `condtrack synth` at their defaults (seed 0); track files bench/out/synth_<scene>.<method>.h5.",
        "",
    ] + synthetic_versus_lk_table(work, extra, paper) if synthetic else [])
