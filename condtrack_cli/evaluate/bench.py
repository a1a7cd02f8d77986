"""The benchmark: every method on every sequence with ground truth, plus a speed case.

``make bench`` runs ``python -m condtrack_cli.evaluate.bench --out bench/results.md``.
Each method runs as its own ``condtrack track`` process (whole-process wall time
and peak resident memory, read with ``os.wait4``), and is scored with the same
code as ``condtrack eval``. Speed (issue 13) is a ratio to a plain OpenCV
Lucas-Kanade script (``plain_lk.py``) run as its own process in the same run,
on a 640x480 synthetic scene and a shared KITTI clip, followed by a profile of
each filter by stage (``speed_table``, ``profile_table``).

Sequences: ``sample_sequences/*`` (queries.csv and tracks.csv shipped) and
``../shared/data/*`` with a tracks.csv (skipped with a message when absent);
for those, the queries are each track's first observation, over tracks with at
least 3 observations, at most ``--max-points`` of them (every k-th track, k
the smallest stride that fits) to bound the run time.

``--batch`` prints only the batch throughput table (``batch_table``);
``--speed`` only the speed comparison and the profile.

``--support SEQUENCE`` prints instead the dominant model's one-step prediction
error by neighbourhood support (the measurement behind ``auto``'s thresholds).
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import subprocess
import sys
import shutil
import time
from pathlib import Path

import numpy as np

from condtrack_cli import registry
from condtrack_cli.evaluate.groundtruth import GroundTruth, load_gt_csv
from condtrack_cli.evaluate.score import score_tracks
from condtrack_cli.io.read import read_tracks

REPO = Path(__file__).resolve().parents[2]


def gt_queries(truth: GroundTruth, min_observations: int = 3, max_points: int | None = None) -> np.ndarray:
    """(Q, 4) rows point_id, frame, x, y: each kept track's first observation.

    Tracks with fewer than ``min_observations`` GT rows are dropped; when more
    than ``max_points`` remain, every k-th is kept (k the smallest that fits).
    """
    counts = truth.known.sum(axis=1)
    keep = np.flatnonzero(counts >= min_observations)
    if max_points is not None and len(keep) > max_points:
        keep = keep[:: int(np.ceil(len(keep) / max_points))]
    first = truth.known[keep].argmax(axis=1)
    xy = truth.gt_xy[keep, first]
    return np.column_stack([truth.point_id[keep], first, xy])


def write_queries(rows: np.ndarray, path: Path) -> None:
    """Write (Q, 4) query rows as the ``point_id,frame,x,y`` CSV that ``track -p`` reads."""
    lines = ["point_id,frame,x,y"] + [f"{int(p)},{int(f)},{x:.4f},{y:.4f}" for p, f, x, y in rows]
    path.write_text("\n".join(lines) + "\n")


def run_track(args: list[str]) -> tuple[float, float, int, str]:
    """Run ``condtrack track ARGS``: (wall seconds, peak RSS MiB, exit code, stderr's last line)."""
    started = time.perf_counter()
    process = subprocess.Popen(
        [sys.executable, "-m", "condtrack_cli", "track", *args, "-q"], stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
    )
    stderr = process.stderr.read().decode()
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - started
    return seconds, usage.ru_maxrss / 1024.0, process.returncode, (stderr.strip().splitlines() or [""])[-1]


def sequences(max_points: int, work: Path) -> list[tuple[str, Path, Path, Path]]:
    """(name, frames folder, queries CSV, GT CSV) of every sequence with ground truth."""
    found = []
    for folder in sorted((REPO / "sample_sequences").glob("*/")):
        if (folder / "tracks.csv").is_file() and (folder / "queries.csv").is_file():
            found.append((f"sample/{folder.name}", folder, folder / "queries.csv", folder / "tracks.csv"))
    shared = REPO.parent / "shared" / "data"
    if not shared.is_dir():
        print(f"bench: {shared} is absent; shared sequences skipped", file=sys.stderr)
        return found
    for folder in sorted(shared.glob("*/")):
        gt_path = folder / "tracks.csv"
        if not gt_path.is_file():
            continue
        rows = gt_queries(load_gt_csv(gt_path), max_points=max_points)
        queries = work / f"{folder.name}.queries.csv"
        write_queries(rows, queries)
        found.append((f"shared/{folder.name}", folder, queries, gt_path))
    return found


def _fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"


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
                f"| {name} | {method} | {len(data.point_id)} | {_fmt(result['delta_avg'])} | {_fmt(result['AJ'])} | "
                f"{_fmt(result['OA'])} | {_fmt(result['cov95'])} | {_fmt(result['median_err'])} | {seconds:.1f} | {ratio} |"
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
            cells = [_fmt(result[key]) for key in ("cov50", "cov90", "cov95", "cov99")]
            nees = "n/a" if result["nees"] is None else f"{result['nees']:.2f}"
            lines.append(f"| {name} | {method} | {' | '.join(cells)} | {nees} | {_fmt(result['cov_finite'])} |")
    return lines


#: Methods of the speed comparison with OpenCV LK (issue 13) and of the profile table.
SPEED_METHODS = ("clf", "auto", "cnlf")

#: The shared clip of the speed comparison on real frames (KITTI, 1242x375).
SPEED_CLIP = "kt3dmoseg_seq005_clip01"


def speed_scenes(work: Path, shared: Path, n_points: int = 500, n_frames: int = 60,
                 size: tuple[int, int] = (640, 480)) -> list[tuple[str, Path, Path]]:
    """(title, frames folder, queries CSV) of the speed cases of issue 13.

    The synthetic camera_motion scene at ``size`` with ``n_points`` uniformly drawn
    points over ``n_frames`` frames (the points within 24 px of the border and those
    the scene hides are still asked for), and the first 20 frames of the shared
    ``SPEED_CLIP`` with the real-video queries of issue 11 (:func:`versus_lk_queries`)
    on them, when the shared data is there.
    """
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    folder = write_scene(make_scene("camera_motion", seed=1, size=size, n_frames=n_frames), work / "speed")
    rng = np.random.default_rng(0)
    margin = 24
    xy = np.column_stack([rng.uniform(margin, size[0] - margin, n_points), rng.uniform(margin, size[1] - margin, n_points)])
    queries = work / "speed.queries.csv"
    write_queries(np.column_stack([np.arange(n_points), np.zeros(n_points), xy]), queries)
    scenes = [(f"synthetic camera_motion {size[0]}x{size[1]}, {n_frames} frames, {n_points} points", folder, queries)]
    clip = shared / SPEED_CLIP
    if (clip / "tracks.csv").is_file():
        rows = versus_lk_queries(load_gt_csv(clip / "tracks.csv"), oxford=False)
        kitti = work / "speed_kitti.queries.csv"
        write_queries(rows, kitti)
        n_clip = len(list(clip.glob("*.png")))
        scenes.append((f"{SPEED_CLIP} 1242x375, {n_clip} frames, {len(rows)} points", clip, kitti))
    return scenes


def run_plain_lk(folder: Path, queries: Path, out: Path) -> tuple[float, float, int, str]:
    """Run the plain OpenCV script (``plain_lk.py``) as its own process: like :func:`run_track`."""
    script = Path(__file__).with_name("plain_lk.py")
    started = time.perf_counter()
    process = subprocess.Popen([sys.executable, str(script), str(folder), str(queries), str(out)],
                               stderr=subprocess.PIPE, stdout=subprocess.DEVNULL)
    stderr = process.stderr.read().decode()
    _, status, usage = os.wait4(process.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - started, usage.ru_maxrss / 1024.0, code, (stderr.strip().splitlines() or [""])[-1]


def speed_table(work: Path, shared: Path, repeats: int = 3) -> list[str]:
    """Markdown: whole-process wall time of each method over the plain OpenCV LK script's, per speed scene (issue 13).

    Per scene, ``repeats`` rounds each run the script (``plain_lk.py``: decode, LK
    with the forward-backward check, CSV out) then each of ``SPEED_METHODS`` (``condtrack
    track``, start-up and writing the HDF5 file included), one process each; the
    table gives the median wall time, its ratio to the script's median of the same
    run and the largest peak RSS.
    """
    methods = ("opencv-lk",) + SPEED_METHODS
    lines = [
        f"Whole-process wall time, median of {repeats} rounds run one after the other (script, then each method), "
        "and its ratio to the plain OpenCV LK script (`condtrack_cli/evaluate/plain_lk.py`: calcOpticalFlowPyrLK "
        "winSize 21, maxLevel 3, forward-backward check 1 px, CSV out) of the same run. Issue 13's targets: "
        "clf <= 2x, auto <= 3x, cnlf <= 5x, peak RSS <= 300 MiB.",
        "",
    ]
    for title, folder, queries in speed_scenes(work, shared):
        times, peaks, failed = {m: [] for m in methods}, {m: 0.0 for m in methods}, {}
        for _ in range(repeats):
            for method in methods:
                if method == "opencv-lk":
                    seconds, rss, code, message = run_plain_lk(folder, queries, work / "speed.lk.csv")
                else:
                    seconds, rss, code, message = run_track(
                        [str(folder), "-p", str(queries), "-m", method, "-o", str(work / f"speed.{method}.h5")])
                if code:
                    failed[method] = message
                times[method].append(seconds)
                peaks[method] = max(peaks[method], rss)
        lk = float(np.median(times["opencv-lk"]))
        lines += [f"Scene: {title}.", "", "| method | wall (s) | × OpenCV LK | peak RSS (MiB) |", "|---|---|---|---|"]
        for method in methods:
            if method in failed:
                lines.append(f"| {method} | failed: {failed[method]} | | |")
                continue
            median = float(np.median(times[method]))
            lines.append(f"| {method} | {median:.2f} | {median / lk:.1f} | {peaks[method]:.0f} |")
            print(lines[-1], file=sys.stderr)
        lines.append("")
    return lines


#: Stages of the profile table: (name, file suffix, function) whose cumulative time is the stage's;
#: the stages are disjoint (none calls another).
PROFILE_STAGES = (
    ("frame decoding (cv2.imread)", "~", "<imread>"),
    ("pyramids and gradients (robust.build_pyramid)", "motion/robust.py", "build_pyramid"),
    ("global robust motion (robust.estimate_from_pyramids)", "motion/robust.py", "estimate_from_pyramids"),
    ("local robust motion (local.local_field)", "motion/local.py", "local_field"),
    ("SSD measurement (ssd.measure)", "measure/ssd.py", "measure"),
)


def profile_shares(profile: Path) -> list[tuple[str, float, int]]:
    """(stage, share of the process's time, calls) from a cProfile file of ``condtrack track``.

    The stages of PROFILE_STAGES; 'filters and pipeline, rest' is the pipeline's time
    (pipeline.run) outside them; 'reading queries, writing the output' the track
    command's outside the pipeline; 'start-up (imports, CLI, configuration)' the rest.
    """
    import pstats

    stats = pstats.Stats(str(profile)).stats  # {(file, line, function): (calls, primitive, tottime, cumtime, callers)}
    total = sum(entry[2] for entry in stats.values())

    def cumulative(suffix: str, function: str) -> tuple[float, int]:
        found = [(entry[3], entry[1]) for (file, _, name), entry in stats.items()
                 if file.endswith(suffix) and name == function]
        return max(found, default=(0.0, 0))  # the outer of wrappers with the same name (ssd.measure)

    rows = [(name, *cumulative(suffix, function)) for name, suffix, function in PROFILE_STAGES]
    pipeline, _ = cumulative("condtrack_cli/pipeline.py", "run")
    command, _ = cumulative("cli/track.py", "track")
    rows.append(("filters and pipeline, rest", pipeline - sum(seconds for _, seconds, _ in rows), 0))
    rows.append(("reading queries, writing the output", command - pipeline, 0))
    rows.append(("start-up (imports, CLI, configuration)", total - command, 0))
    return [(name, seconds / total, calls) for name, seconds, calls in rows]


def profile_table(work: Path, shared: Path) -> list[str]:
    """Markdown: where the time goes (cProfile of one ``condtrack track`` process per method and speed scene)."""
    scenes = speed_scenes(work, shared)
    lines = [
        "Share of one `condtrack track` process's time by stage (cProfile, which slows Python-level code more than "
        "OpenCV/numpy calls), calls = calls of the stage's function. Scenes: "
        + "; ".join(f"({chr(97 + i)}) {title}" for i, (title, _, _) in enumerate(scenes)) + ". "
        "`python -m cProfile -o out.prof -m condtrack_cli track FRAMES -p QUERIES -m METHOD -o out.h5 -q`.",
        "",
        "| stage | " + " | ".join(f"{m} ({chr(97 + i)})" for i in range(len(scenes)) for m in SPEED_METHODS) + " |",
        "|---|" + "---|" * (len(scenes) * len(SPEED_METHODS)),
    ]
    columns = []
    for index, (_, folder, queries) in enumerate(scenes):
        for method in SPEED_METHODS:
            profile = work / f"profile.{index}.{method}.prof"
            subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), "-m", "condtrack_cli", "track",
                            str(folder), "-p", str(queries), "-m", method, "-o", str(work / "profile.h5"), "-q"],
                           check=True, stdout=subprocess.DEVNULL)
            columns.append(profile_shares(profile))
    for row, (name, _, _) in enumerate(columns[0]):
        cells = [f"{column[row][1]:.0%}" + (f" ({column[row][2]})" if column[row][2] else "") for column in columns]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def batch_table(work: Path, n_clips: int = 8, n_frames: int = 20, size: tuple[int, int] = (320, 240),
                method: str = "clf") -> list[str]:
    """Markdown rows: batch throughput (clips per minute) of ``track --out-dir -j J`` for J = 1, 2, 4, ... up to the cores.

    ``n_clips`` synthetic camera_motion clips (seeds 0..n_clips-1) with detected
    points, one whole ``condtrack track`` process per J (start-up and the
    workers' start included). Efficiency per core: throughput(J) / (J x
    throughput(1)); 1.0 is linear scaling. CPU seconds (user + system, all the
    run's processes) tell the work done from the wait for a busy machine.
    """
    import resource

    from condtrack_cli.frames.synthetic import make_scene, write_scene
    from condtrack_cli.threads import cores

    clips = [str(write_scene(make_scene("camera_motion", seed=i, size=size, n_frames=n_frames), work / "batch" / f"clip{i:03d}"))
             for i in range(n_clips)]
    available = cores()
    jobs = sorted({j for j in (1, 2, 4, 8, 16, 32, 64) if j <= available} | {available})
    lines = [
        f"Batch: {n_clips} clips of {n_frames} frames at {size[0]}x{size[1]} (synthetic camera_motion, detected points), "
        f"`condtrack track CLIPS --out-dir DIR -m {method} -j J`, whole-process wall time; {available} cores.",
        "",
        "| -j | wall (s) | clips / min | efficiency per core | CPU (s) |",
        "|---|---|---|---|---|",
    ]
    single = None
    for count in jobs:
        out_dir = work / "batch" / f"out-j{count}"
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        seconds, _, code, message = run_track([*clips, "-m", method, "--out-dir", str(out_dir), "-j", str(count)])
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
        if code != 0:
            lines.append(f"| {count} | failed: {message} | | | |")
            continue
        rate = n_clips / seconds * 60.0
        single = rate if count == 1 else single
        efficiency = f"{rate / (count * single):.2f}" if single else "n/a"
        lines.append(f"| {count} | {seconds:.1f} | {rate:.1f} | {efficiency} | {cpu:.1f} |")
        print(lines[-1], file=sys.stderr)
    return lines


#: Bins of the neighbourhood support for ``support_table``.
SUPPORT_BINS = (0.0, 0.4, 0.6, 0.8, 1.0001)


def support_table(folder: Path, window: int = 32) -> list[str]:
    """Markdown rows: the dominant model's one-step prediction error on a sequence's GT, by support.

    For every GT track seen on frames k-1 and k, the error |x_k - (x_{k-1} +
    U(x_{k-1}))| of the default global fit, binned by the mean robust weight
    over the ``window`` square around x_{k-1} (``neighbourhood_support``): the
    measurement behind ``auto``'s thresholds and the misfit term of Q_k.
    """
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.motion.robust import GlobalMotion, RobustMotionSettings, displacement, neighbourhood_support
    from condtrack_cli.types import Frame

    truth = load_gt_csv(folder / "tracks.csv")
    motion = GlobalMotion(RobustMotionSettings())
    support, error, prev = [], [], None
    for index, image in enumerate(open_frames(FrameSettings(), folder)):
        frame = Frame(index, image)
        if prev is not None:
            both = truth.known[:, index - 1] & truth.known[:, index]
            x, x_next = truth.gt_xy[both, index - 1], truth.gt_xy[both, index]
            fit = motion.fit(prev, frame)
            support.append(neighbourhood_support(fit, x, window))
            error.append(np.linalg.norm(x + displacement(fit, x) - x_next, axis=1))
        prev = frame
    support, error = np.concatenate(support), np.concatenate(error)
    lines = [f"One-step error of the dominant model on {folder.name}, by support:", "",
             "| support | share | median error (px) |", "|---|---|---|"]
    for low, high in zip(SUPPORT_BINS[:-1], SUPPORT_BINS[1:]):
        inside = (support >= low) & (support < high)
        median = f"{np.median(error[inside]):.2f}" if inside.any() else "n/a"
        lines.append(f"| [{low:.1f}, {min(high, 1.0):.1f}{']' if high > 1 else ')'} | {inside.mean():.2f} | {median} |")
    return lines


# --------------------------------------------------------------------------- issue 11: against OpenCV LK

#: Methods of the real-video table, after the OpenCV LK baseline.
VERSUS_LK_METHODS = ("auto", "clf", "cnlf", "stk")
#: Synthetic scenes of ``condtrack synth`` scored against LK, each at its defaults (seed 0).
VERSUS_LK_SCENES = ("camera_motion", "occlusion", "ring", "illumination", "fast")


def versus_lk_queries(truth: GroundTruth, oxford: bool, max_points: int = 300) -> np.ndarray:
    """Issue 11's real-video queries: first observation of tracks with >= 5 observations (>= 2 on Oxford sets)."""
    return gt_queries(truth, min_observations=2 if oxford else 5, max_points=max_points)


def score_versus_lk(folder: Path, queries: Path, truth: GroundTruth, work: Path, stem: str) -> dict:
    """{column: (metrics dict, wall seconds)} for OpenCV LK and ``VERSUS_LK_METHODS`` on one sequence.

    LK runs in this process (frame reading and both LK directions timed); each
    condtrack method runs as its own ``condtrack track`` process (whole-process
    wall time, start-up included). A failed method maps to (None, message).
    """
    from condtrack_cli.evaluate.opencv_lk import opencv_lk
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.queries import read_queries

    started = time.perf_counter()
    lk = opencv_lk(folder, read_queries(queries, open_frames(FrameSettings(), folder).info))
    results = {"lk": (score_tracks(lk, truth, "first")[0], time.perf_counter() - started)}
    for method in VERSUS_LK_METHODS:
        out = work / f"{stem}.{method}.h5"
        seconds, _, code, message = run_track([str(folder), "-p", str(queries), "-m", method, "-o", str(out)])
        results[method] = (None, message) if code else (score_tracks(read_tracks(out)[0], truth, "first")[0], seconds)
    return results


def _cell(result: tuple) -> str:
    metrics, seconds = result
    return f"failed: {seconds}" if metrics is None else f"{_fmt(metrics['delta_avg'])} ({seconds:.0f} s)"


def _delta(results: dict, column: str) -> float:
    metrics = results[column][0]
    return np.nan if metrics is None or metrics["delta_avg"] is None else metrics["delta_avg"]


def _check(ok: bool, text: str) -> str:
    return f"- [{'x' if ok else ' '}] {'pass' if ok else 'FAIL'}: {text}"


def real_video_table(work: Path, shared: Path, max_points: int = 300) -> list[str]:
    """Markdown: <δ_avg of OpenCV LK and each method per real set of ``shared``, then issue 11's done-when checks."""
    columns = ("lk",) + VERSUS_LK_METHODS
    lines = ["| set | points | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    per_set = {}
    for folder in sorted(shared.glob("*/")) if shared.is_dir() else []:
        if not (folder / "tracks.csv").is_file():
            continue
        truth = load_gt_csv(folder / "tracks.csv")
        rows = versus_lk_queries(truth, folder.name.startswith("oxford"), max_points)
        queries = work / f"lk11_{folder.name}.queries.csv"
        write_queries(rows, queries)
        per_set[folder.name] = score_versus_lk(folder, queries, truth, work, f"lk11_{folder.name}")
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
    return lines + ["", "Done-when checks of issue 11 (real video):", ""] + checks


def _better_filter_checks(per_set: dict) -> list[str]:
    """One check per set: auto within 0.01 of the better of clf and cnlf."""
    checks = []
    for name, results in per_set.items():
        auto, best = _delta(results, "auto"), max(_delta(results, "clf"), _delta(results, "cnlf"))
        checks.append(_check(auto >= best - 0.01, f"{name}: auto {auto:.3f} >= better filter {best:.3f} - 0.01"))
    return checks


def synthetic_versus_lk_table(work: Path) -> list[str]:
    """Markdown: the ``condtrack synth`` scenes at their defaults, LK and each method, then issue 11's checks."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    columns = ("lk",) + VERSUS_LK_METHODS
    lines = ["| scene | points | " + " | ".join(f"{c} <δ / AJ / OA" for c in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    per_scene = {}
    for scene in VERSUS_LK_SCENES:
        folder = write_scene(make_scene(scene), work / f"synth_{scene}")
        truth = load_gt_csv(folder / "tracks.csv")
        per_scene[scene] = score_versus_lk(folder, folder / "queries.csv", truth, work, f"synth_{scene}")
        cells = [
            "failed" if m is None else " / ".join(_fmt(m[key]) for key in ("delta_avg", "AJ", "OA"))
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
    return lines + ["", "Done-when checks of issue 11 (synthetic scenes):", ""] + checks


def versus_lk_section(work: Path, shared: Path = REPO.parent / "shared" / "data") -> list[str]:
    """The results.md section of issue 11: real video and synthetic scenes against OpenCV LK maxLevel 3."""
    return [
        "## Against OpenCV LK (issue 11)",
        "",
        "OpenCV LK: `calcOpticalFlowPyrLK` winSize 21, maxLevel 3, forward-backward check 1 px "
        "(`condtrack_cli/evaluate/opencv_lk.py`), run and timed in this process; the methods' times are whole "
        "`condtrack track` processes. Real sets: queries = first observation of tracks with >= 5 observations "
        "(>= 2 on the Oxford sets), at most 300 per set taken evenly; <δ_avg in the 'first' query mode; "
        "cells are <δ_avg (wall seconds). Track files: bench/out/lk11_<set>.<method>.h5.",
        "",
    ] + real_video_table(work, shared) + [
        "",
        "Synthetic scenes of `condtrack synth` at their defaults (seed 0); track files bench/out/synth_<scene>.<method>.h5.",
        "",
    ] + synthetic_versus_lk_table(work)


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()} cores, {cpu}"


def commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    except OSError:
        return "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results.md")
    parser.add_argument("--max-points", type=int, default=1000, help="most query points per shared sequence")
    parser.add_argument("--work", type=Path, default=REPO / "bench" / "out",
                        help="folder for the queries and track files (emptied first; kept for `condtrack eval`)")
    parser.add_argument("--support", type=Path, metavar="SEQUENCE",
                        help="only print the dominant model's one-step error by support on SEQUENCE (with tracks.csv)")
    parser.add_argument("--batch", action="store_true", help="only print the batch throughput table")
    parser.add_argument("--speed", action="store_true",
                        help="only print the speed comparison with OpenCV LK and the profile table (issue 13)")
    parser.add_argument("--shared-data", type=Path, default=REPO.parent / "shared" / "data",
                        help="folder of the real sets for the section against OpenCV LK")
    parser.add_argument("--versus-lk", action="store_true",
                        help="only print the section against OpenCV LK (issue 11); results.md is not written")
    args = parser.parse_args()
    if args.versus_lk:
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(versus_lk_section(args.work, args.shared_data)))
        return
    if args.support:
        print("\n".join(support_table(args.support)))
        return
    if args.speed:
        shutil.rmtree(args.work / "speed", ignore_errors=True)
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(speed_table(args.work, args.shared_data) + ["## Profile", ""]
                        + profile_table(args.work, args.shared_data)))
        return
    if args.batch:
        shutil.rmtree(args.work / "batch", ignore_errors=True)
        print("\n".join(batch_table(args.work)))
        return
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    accuracy = accuracy_table(args.max_points, args.work)
    speed = speed_table(args.work, args.shared_data)
    profile = profile_table(args.work, args.shared_data)
    batch = batch_table(args.work)
    versus_lk = versus_lk_section(args.work, args.shared_data)
    header = [
        "# condtrack benchmark",
        "",
        f"- date: {datetime.date.today().isoformat()}",
        f"- machine: {machine()}",
        f"- commit: {commit()}",
        "- command: `make bench`",
        "",
        "## Accuracy (TAP-Vid 'first' query mode; shared sets: queries = first observation of tracks "
        f"with >= 3 observations, at most {args.max_points} per sequence)",
        "",
        "OA and AJ are n/a where the ground truth has no occluded rows. cov95 is n/a for methods without covariance.",
        "Track files stay in bench/out/ (`<sequence>.<method>.h5`, queries beside them): "
        "`condtrack eval bench/out/<file>.h5 <ground truth>` gives the row's numbers.",
        "",
    ]
    calibration = [
        "", "## Covariance calibration (same track files; 'first' query mode, GT-visible rows after the query)", "",
        "covP: share of the ground truth inside the predicted ellipse of level P % (ideal P/100); NEES: mean "
        "d^T C^-1 d over the rows with a finite covariance (ideal 2); finite: share of those rows.", "",
    ] + calibration_table(args.max_points, args.work)
    text = "\n".join(header + accuracy + calibration + ["", "## Speed (issue 13)", ""] + speed + ["## Profile", ""] + profile + ["", "## Many clips", ""] + batch + [""] + versus_lk) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"bench: wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
