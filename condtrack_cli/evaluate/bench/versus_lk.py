"""The section against OpenCV LK maxLevel 3 (issue 11): real sets and synthetic scenes, with the done-when checks.

The same track files also give the coverage of each method's reported covariance (issue 12), with its targets.
"""

from __future__ import annotations

import sys
import time
from fnmatch import fnmatch
from pathlib import Path

import numpy as np

from condtrack_cli.evaluate.bench.common import REPO, fmt, gt_queries, run_track, write_queries
from condtrack_cli.evaluate.groundtruth import GroundTruth, load_gt_csv
from condtrack_cli.evaluate.score import score_tracks
from condtrack_cli.io.read import read_tracks


#: Baselines run in this process: OpenCV LK (issue 11) and chained DIS MEDIUM (issue 45).
BASELINES = ("lk", "dis")

#: Methods of the real-video table, after the baselines.
VERSUS_LK_METHODS = ("auto", "clf", "cnlf", "stk")

#: Every column the section can run without the paper preset (``--methods`` picks among these).
COLUMNS = BASELINES + VERSUS_LK_METHODS

#: Methods whose rows carry a covariance: the coverage tables of issues 12, 27 and 45.
COVARIANCE_METHODS = ("auto", "clf", "cnlf")

#: Columns of the per-group tables of issue 45.
GROUP_COLUMNS = ("lk", "dis", "clf", "cnlf", "auto")

#: The ``paper`` preset (issue 29): the method as published, run with each of these methods beside the
#: defaults; its columns are named "paper <method>". Its CNLF regresses the motion per particle: slow.
PAPER_CONFIG = REPO / "configs" / "paper.yaml"
PAPER_METHODS = ("clf", "cnlf", "auto")

#: Issue 45's calibration bands on a group's mean: (metric key, lowest, highest) share of the truth inside the
#: ellipse of each row's Student-t distribution.
GROUP_COVERAGE_TARGETS = (("cov50", 0.42, 0.62), ("cov90", 0.85, 0.95), ("cov95", 0.90, 0.98), ("cov99", 0.97, 1.0))
#: Issue 45's bands on every single set; the share of rows with a finite covariance kept from issue 27.
SET_COVERAGE_TARGETS = (("cov50", 0.35, 0.75), ("cov95", 0.85, 0.99), ("cov_finite", 0.95, 1.0))

#: Groups of real sets (name, glob of set names), one table each; a set matching none goes to "other".
REAL_GROUPS = (("KITTI", "kt3dmoseg_*"), ("face", "dudek_*"), ("animal", "badja_*"), ("Oxford", "oxford_*"))

#: Synthetic scenes of ``condtrack synth`` scored against the baselines, each at its defaults (seed 0).
VERSUS_LK_SCENES = ("camera_motion", "occlusion", "ring", "illumination", "fast")
#: The non-rigid scene family (issue 45): parameters may be tuned on ``NONRIGID_TUNE_SEEDS`` only; the synthetic
#: table reports ``NONRIGID_REPORT_SEEDS`` (rows ``nonrigid_<seed>``).
NONRIGID_TUNE_SEEDS = (1, 2, 3)
NONRIGID_REPORT_SEEDS = (0, 4, 5)


def versus_lk_queries(truth: GroundTruth, oxford: bool, max_points: int = 300) -> np.ndarray:
    """Issue 11's real-video queries: first observation of tracks with >= 5 observations (>= 2 on Oxford sets)."""
    return gt_queries(truth, min_observations=2 if oxford else 5, max_points=max_points)


def paper_columns(paper: tuple[str, ...]) -> tuple[str, ...]:
    """The columns of the ``paper`` preset run with each method of ``paper``."""
    return tuple(f"paper {method}" for method in paper)


def selected(names, patterns: tuple[str, ...] | None) -> list:
    """The ``names`` matching any glob of ``patterns`` (all of them when ``patterns`` is None), in order."""
    return [name for name in names if patterns is None or any(fnmatch(name, pattern) for pattern in patterns)]


def score_versus_lk(folder: Path, queries: Path, truth: GroundTruth, work: Path, stem: str,
                    extra: tuple[str, ...] = (), paper: tuple[str, ...] = PAPER_METHODS,
                    methods: tuple[str, ...] = COLUMNS) -> dict:
    """{column: (metrics dict, wall seconds)} for the baselines and methods of ``methods`` and the ``paper`` preset
    with each method of ``paper`` (column "paper <method>", ``-c configs/paper.yaml``) on one sequence.

    The baselines (OpenCV LK, chained DIS) run in this process (frame reading and both flow directions timed);
    each condtrack method runs as its own ``condtrack track`` process (whole-process wall time, start-up included),
    with the ``extra`` arguments (e.g. ``--set`` overrides). A failed method maps to (None, message).
    """
    from condtrack_cli.evaluate.opencv_dis import opencv_dis
    from condtrack_cli.evaluate.opencv_lk import opencv_lk
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.queries import read_queries

    results = {}
    for column, baseline in (("lk", opencv_lk), ("dis", opencv_dis)):
        if column in methods:
            started = time.perf_counter()
            tracks = baseline(folder, read_queries(queries, open_frames(FrameSettings(), folder).info))
            results[column] = (score_tracks(tracks, truth, "first")[0], time.perf_counter() - started)
    runs = [(method, method, method, ()) for method in VERSUS_LK_METHODS if method in methods]  # column, -m, file, -c
    runs += [(column, method, f"paper-{method}", ("-c", str(PAPER_CONFIG)))
             for method, column in zip(paper, paper_columns(paper))]
    for column, method, name, config in runs:
        out = work / f"{stem}.{name}.h5"
        seconds, _, code, message = run_track([str(folder), "-p", str(queries), *config, "-m", method, "-o", str(out),
                                               *extra])
        results[column] = (None, message) if code else (score_tracks(read_tracks(out)[0], truth, "first")[0], seconds)
    return results


def _cell(result: tuple) -> str:
    metrics, seconds = result
    return f"failed: {seconds}" if metrics is None else f"{fmt(metrics['delta_avg'])} ({seconds:.0f} s)"


def _value(results: dict, column: str, key: str = "delta_avg") -> float:
    """``key`` of ``column``'s metrics; NaN when the column was not run, failed or has no such value."""
    metrics = results.get(column, (None,))[0]
    return np.nan if metrics is None or metrics[key] is None else float(metrics[key])


def _check(ok: bool, text: str) -> str:
    return f"- [{'x' if ok else ' '}] {'pass' if ok else 'FAIL'}: {text}"


def real_video_table(work: Path, shared: Path, max_points: int = 300, extra: tuple[str, ...] = (),
                     paper: tuple[str, ...] = PAPER_METHODS, methods: tuple[str, ...] = COLUMNS,
                     sets: tuple[str, ...] | None = None) -> list[str]:
    """Markdown: <δ_avg of the baselines, each method of ``methods`` and the paper preset's per real set of ``shared``
    (those matching a glob of ``sets``), issue 11's and issue 45's done-when checks, then one table per group of
    sets with its calibration checks (``group_tables``)."""
    columns = tuple(c for c in COLUMNS if c in methods) + paper_columns(paper)
    lines = ["| set | points | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    per_set, points = {}, {}
    folders = sorted(shared.glob("*/")) if shared.is_dir() else []
    for folder in [f for f in folders if selected([f.name], sets)]:
        if not (folder / "tracks.csv").is_file():
            continue
        truth = load_gt_csv(folder / "tracks.csv")
        rows = versus_lk_queries(truth, folder.name.startswith("oxford"), max_points)
        queries = work / f"lk11_{folder.name}.queries.csv"
        write_queries(rows, queries)
        per_set[folder.name] = score_versus_lk(folder, queries, truth, work, f"lk11_{folder.name}", extra, paper, methods)
        points[folder.name] = len(rows)
        lines.append(f"| {folder.name} | {len(rows)} | " + " | ".join(_cell(per_set[folder.name][c]) for c in columns) + " |")
        print(lines[-1], file=sys.stderr)
    if not per_set:
        return [f"{shared} holds no set with a tracks.csv" + (f" matching {','.join(sets)}" if sets else "")
                + ": no real-video table."]
    kitti = [name for name in per_set if name.startswith("kt3dmoseg")]
    if kitti:
        mean = {c: float(np.mean([_value(per_set[n], c) for n in kitti])) for c in columns}
        lines.append("| KITTI mean | | " + " | ".join(f"{mean[c]:.3f}" for c in columns) + " |")
    return lines + ["", "Done-when checks of issues 11 and 45 (real video; those whose columns ran):", ""] + \
        real_video_checks(per_set, columns) + [
        "", "Coverage of each row's predictive distribution on the same runs (issues 12 and 27; `condtrack eval` keys):", ""
    ] + coverage_table(per_set, "set", paper) + [""] + group_tables(per_set, points, REAL_GROUPS)


def real_video_checks(per_set: dict, columns: tuple[str, ...]) -> list[str]:
    """Issue 11's checks and issue 45's targets on the real sets, each where its columns ran and its sets are."""
    def ran(*needed: str) -> bool:
        return all(c in columns for c in needed)

    def delta(name: str, column: str) -> float:
        return _value(per_set[name], column)

    kitti = [name for name in per_set if name.startswith("kt3dmoseg")]
    face = [name for name in per_set if name.startswith("dudek")]
    mean = {c: float(np.mean([delta(n, c) for n in kitti])) if kitti else np.nan for c in columns}
    checks = []
    if kitti and ran("auto", "lk"):
        checks.append(_check(mean["auto"] >= mean["lk"] + 0.07,
                             f"KITTI mean of auto {mean['auto']:.3f} >= LK mean {mean['lk']:.3f} + 0.07"))
        checks += [_check(delta(n, "auto") >= delta(n, "lk"), f"{n}: auto {delta(n, 'auto'):.3f} >= LK "
                          f"{delta(n, 'lk'):.3f}") for n in kitti]
    if kitti and ran("auto", "dis"):
        ahead = sum(delta(n, "auto") >= delta(n, "dis") for n in kitti)
        checks.append(_check(mean["auto"] >= mean["dis"],
                             f"KITTI mean of auto {mean['auto']:.3f} >= chained DIS mean {mean['dis']:.3f}"))
        checks.append(_check(ahead >= len(kitti) - 1, f"auto >= chained DIS on {ahead} of {len(kitti)} KITTI clips "
                             f"(at least {len(kitti) - 1})"))
    if ran("auto", "lk"):
        for name in [n for n in ("oxford_dinosaur", "oxford_merton1") if n in per_set] + face:
            checks.append(_check(delta(name, "auto") >= delta(name, "lk"),
                                 f"{name}: auto {delta(name, 'auto'):.3f} >= LK {delta(name, 'lk'):.3f}"))
        if face:
            auto, lk = (float(np.mean([delta(n, c) for n in face])) for c in ("auto", "lk"))
            checks.append(_check(auto >= lk + 0.06, f"face mean of auto {auto:.3f} >= LK mean {lk:.3f} + 0.06"))
    if "badja_camel" in per_set and ran("auto"):
        auto = delta("badja_camel", "auto")
        if ran("lk"):
            checks.append(_check(auto >= delta("badja_camel", "lk") + 0.05,
                                 f"badja_camel: auto {auto:.3f} >= LK {delta('badja_camel', 'lk'):.3f} + 0.05"))
        if ran("dis"):
            checks.append(_check(auto >= delta("badja_camel", "dis"),
                                 f"badja_camel: auto {auto:.3f} >= chained DIS {delta('badja_camel', 'dis'):.3f}"))
        cov95 = _value(per_set["badja_camel"], "auto", "cov95")
        checks.append(_check(cov95 >= 0.80, f"badja_camel: auto cov95 {cov95:.3f} >= 0.80"))
    if ran("auto", "clf", "cnlf"):
        checks += _better_filter_checks(per_set)
    if ran("clf", "lk"):
        for name in kitti + [n for n in ("oxford_dinosaur",) if n in per_set]:
            checks.append(_check(delta(name, "clf") >= delta(name, "lk"),
                                 f"{name}: clf {delta(name, 'clf'):.3f} >= LK {delta(name, 'lk'):.3f}"))
    return checks


def _better_filter_checks(per_set: dict) -> list[str]:
    """One check per set: auto within 0.01 of the better of clf and cnlf."""
    checks = []
    for name, results in per_set.items():
        auto, best = _value(results, "auto"), max(_value(results, "clf"), _value(results, "cnlf"))
        checks.append(_check(auto >= best - 0.01, f"{name}: auto {auto:.3f} >= better filter {best:.3f} - 0.01"))
    return checks


def coverage_table(per_set: dict, label: str, paper: tuple[str, ...] = ()) -> list[str]:
    """Markdown: coverage under each row's Student-t and read as Gaussian, finite share, NEES and cov50_rescaled of
    ``COVARIANCE_METHODS`` that ran (and the paper preset's columns of ``paper``) per set; the bands are checked by
    ``group_tables``.

    per_set: {set: {method: (metrics dict, seconds)}} as ``score_versus_lk`` returns; label: the first column's name.
    """
    keys = ("cov50", "cov90", "cov95", "cov99", "cov50_gauss", "cov90_gauss", "cov95_gauss", "cov99_gauss",
            "cov_finite", "nees", "cov50_rescaled")
    lines = [f"| {label} | method | " + " | ".join(keys) + " |", "|---|---|" + "---|" * len(keys)]
    for name, results in per_set.items():
        for method in [m for m in COVARIANCE_METHODS + paper_columns(paper) if m in results]:
            metrics = results[method][0]
            if metrics is None:
                lines.append(f"| {name} | {method} | failed |")
                continue
            lines.append(f"| {name} | {method} | " + " | ".join(fmt(metrics[key]) for key in keys) + " |")
    return lines


def group_tables(per_set: dict, points: dict, groups: tuple[tuple[str, str], ...]) -> list[str]:
    """Markdown: one table per group of sets (issue 45): <δ_avg of ``GROUP_COLUMNS`` that ran and the Student-t
    coverage cov50 / cov90 / cov95 / cov99 of each covariance method per set, the group's mean row, then the checks
    of ``GROUP_COVERAGE_TARGETS`` on the group's mean and of ``SET_COVERAGE_TARGETS`` on each set.

    per_set: {set: {column: (metrics dict, seconds)}} as ``score_versus_lk`` returns; points: {set: query count};
    groups: (group name, glob of set names); sets matching none form the group "other".
    """
    members = {name: selected(per_set, (pattern,)) for name, pattern in groups}
    grouped = {s for names in members.values() for s in names}
    members["other"] = [s for s in per_set if s not in grouped]
    levels = tuple(key for key, _, _ in GROUP_COVERAGE_TARGETS)
    lines = []
    for group, names in members.items():
        if not names:
            continue
        ran = [c for c in GROUP_COLUMNS if c in per_set[names[0]]]
        covariance = [c for c in ran if c in COVARIANCE_METHODS]
        lines += [f"### {group}", "",
                  "| set | points | " + " | ".join(ran) + " | " + " | ".join(f"{m} cov50 / 90 / 95 / 99" for m in covariance)
                  + " |", "|---|---|" + "---|" * (len(ran) + len(covariance))]
        values = {n: {(c, k): _value(per_set[n], c, k) for c in ran for k in ("delta_avg",) + levels + ("cov_finite",)}
                  for n in names}
        mean = {key: float(np.mean([values[n][key] for n in names])) for key in values[names[0]]}

        def row(label: str, count: str, value: dict) -> str:
            return (f"| {label} | {count} | " + " | ".join(f"{value[c, 'delta_avg']:.3f}" for c in ran) + " | "
                    + " | ".join(" / ".join(f"{value[m, k]:.2f}" for k in levels) for m in covariance) + " |")

        lines += [row(n, str(points[n]), values[n]) for n in names] + [row(f"{group} mean", "", mean)]
        checks = []
        for method in covariance:
            checks += [_check(low <= mean[method, key] <= high,
                              f"{group} mean {key} of {method} {mean[method, key]:.3f} in [{low:.2f}, {high:.2f}]")
                       for key, low, high in GROUP_COVERAGE_TARGETS]
            for key, low, high in SET_COVERAGE_TARGETS:
                misses = [f"{n} {values[n][method, key]:.3f}" for n in names
                          if not low <= values[n][method, key] <= high]
                checks.append(_check(not misses, f"{key} of {method} in [{low:.2f}, {high:.2f}] on "
                                     f"{len(names) - len(misses)} of {len(names)} sets"
                                     + (f"; not on: {', '.join(misses)}" if misses else "")))
        lines += ["", f"Calibration bands of issue 45 ({group}; Student-t):", ""] + checks + [""]
    return lines


def synthetic_scenes(nonrigid_seeds: tuple[int, ...] = NONRIGID_REPORT_SEEDS) -> list[tuple[str, str, int]]:
    """(row name, scene, seed) of the synthetic table: ``VERSUS_LK_SCENES`` at seed 0, then ``nonrigid`` at each
    seed of ``nonrigid_seeds`` (rows ``nonrigid_<seed>``)."""
    return [(scene, scene, 0) for scene in VERSUS_LK_SCENES] + [(f"nonrigid_{s}", "nonrigid", s) for s in nonrigid_seeds]


def synthetic_versus_lk_table(work: Path, extra: tuple[str, ...] = (), paper: tuple[str, ...] = PAPER_METHODS,
                              methods: tuple[str, ...] = COLUMNS, sets: tuple[str, ...] | None = None,
                              nonrigid_seeds: tuple[int, ...] = NONRIGID_REPORT_SEEDS) -> list[str]:
    """Markdown: the ``synthetic_scenes`` (those matching a glob of ``sets``), the baselines, each method of
    ``methods`` and the paper preset's, issue 11's checks, then the synthetic group's table and calibration checks."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    columns = tuple(c for c in COLUMNS if c in methods) + paper_columns(paper)
    lines = ["| scene | points | " + " | ".join(f"{c} <δ / AJ / OA" for c in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    per_scene, points = {}, {}
    scenes = synthetic_scenes(nonrigid_seeds)
    for name, scene, seed in [row for row in scenes if selected([row[0]], sets)]:
        folder = write_scene(make_scene(scene, seed), work / f"synth_{name}")
        truth = load_gt_csv(folder / "tracks.csv")
        per_scene[name] = score_versus_lk(folder, folder / "queries.csv", truth, work, f"synth_{name}", extra, paper,
                                          methods)
        points[name] = len(truth.point_id)
        cells = [
            "failed" if m is None else " / ".join(fmt(m[key]) for key in ("delta_avg", "AJ", "OA"))
            for m, _ in (per_scene[name][c] for c in columns)
        ]
        lines.append(f"| {name} | {points[name]} | " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr)
    if not per_scene:
        return [f"no synthetic scene matches {','.join(sets or ())}: no synthetic table."]
    checks = _synthetic_checks(per_scene, columns)
    return lines + ["", "Done-when checks of issue 11 (synthetic scenes; those whose columns ran):", ""] + checks + [
        "", "Coverage of each row's predictive distribution on the same runs (issues 12 and 27; `condtrack eval` keys):", ""
    ] + coverage_table(per_scene, "scene", paper) + [""] + group_tables(per_scene, points, (("synthetic", "*"),))


def _synthetic_checks(per_scene: dict, columns: tuple[str, ...]) -> list[str]:
    """Issue 11's checks on the synthetic scenes, each where its columns ran: auto's mean <δ_avg, AJ and OA (AJ and
    OA over the scenes that have them: n/a where the truth has no occluded row, as nonrigid's), auto >= LK per
    scene, auto within 0.01 of the better filter."""
    checks = []
    if "auto" in columns:
        values = {key: [v for v in (_value(r, "auto", key) for r in per_scene.values()) if not np.isnan(v)]
                  for key in ("delta_avg", "AJ", "OA")}
        means = {key: float(np.mean(v)) if v else np.nan for key, v in values.items()}
        checks += [
            _check(means["delta_avg"] >= 0.88, f"auto mean <δ_avg {means['delta_avg']:.3f} >= 0.88"),
            _check(means["AJ"] >= 0.75, f"auto mean AJ {means['AJ']:.3f} >= 0.75 ({len(values['AJ'])} scenes)"),
            _check(means["OA"] >= 0.90, f"auto mean OA {means['OA']:.3f} >= 0.90 ({len(values['OA'])} scenes)"),
        ]
        if "lk" in columns:
            for scene, results in per_scene.items():
                auto, lk = _value(results, "auto"), _value(results, "lk")
                checks.append(_check(auto >= lk, f"{scene}: auto {auto:.3f} >= LK {lk:.3f}"))
    if all(c in columns for c in ("auto", "clf", "cnlf")):
        checks += _better_filter_checks(per_scene)
    return checks


def versus_lk_section(work: Path, shared: Path = REPO.parent / "shared" / "data", extra: tuple[str, ...] = (),
                      paper: tuple[str, ...] = PAPER_METHODS, max_points: int = 300, synthetic: bool = True,
                      methods: tuple[str, ...] = COLUMNS, sets: tuple[str, ...] | None = None,
                      nonrigid_seeds: tuple[int, ...] = NONRIGID_REPORT_SEEDS) -> list[str]:
    """The results.md section of issues 11 and 45: real video and synthetic scenes against OpenCV LK maxLevel 3 and
    chained DIS.

    extra: arguments added to every ``condtrack track`` (``--set`` overrides, to measure a variant).
    paper: the methods run with the ``paper`` preset as extra columns (issue 29). max_points: most queries
    per real set. synthetic: also the synthetic scenes' table. methods: the columns of ``COLUMNS`` to run.
    sets: globs of the set and scene names to run (None: all). nonrigid_seeds: the seeds of the ``nonrigid``
    scene in the synthetic table (``NONRIGID_REPORT_SEEDS``, or ``NONRIGID_TUNE_SEEDS`` while tuning).
    """
    return [
        "## Against OpenCV LK and chained DIS (issues 11 and 45)",
        "",
        "OpenCV LK: `calcOpticalFlowPyrLK` winSize 21, maxLevel 3, forward-backward check 1 px "
        "(`condtrack_cli/evaluate/opencv_lk.py`); chained DIS: `DISOpticalFlow` preset MEDIUM, forward flow sampled "
        "bilinearly at the point, visible where the round trip through the backward flow returns within 1 px "
        "(`condtrack_cli/evaluate/opencv_dis.py`); both run and timed in this process; the methods' times are whole "
        "`condtrack track` processes. Real sets: queries = first observation of tracks with >= 5 observations "
        f"(>= 2 on the Oxford sets), at most {max_points} per set taken evenly; <δ_avg in the 'first' query mode; "
        f"cells are <δ_avg (wall seconds). Track files: bench/out/lk11_<set>.<method>.h5. Columns 'paper <method>': "
        "`condtrack track -c configs/paper.yaml -m <method>`, the method as published (issue 29; "
        "bench/out/lk11_<set>.paper-<method>.h5).",
        "",
    ] + real_video_table(work, shared, max_points, extra, paper, methods, sets) + ([
        "",
        "Synthetic scenes of `condtrack synth` at their defaults (seed 0; `nonrigid` at seeds "
        f"{', '.join(map(str, nonrigid_seeds))}); track files bench/out/synth_<scene>.<method>.h5.",
        "",
    ] + synthetic_versus_lk_table(work, extra, paper, methods, sets, nonrigid_seeds) if synthetic else [])
