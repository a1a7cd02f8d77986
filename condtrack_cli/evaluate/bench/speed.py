"""Speed against a plain OpenCV LK script (issue 13) and against an earlier commit (issue 45), the profile by stage,
and batch throughput (issue 14)."""

from __future__ import annotations

import compileall
import io
import os
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import numpy as np

from condtrack_cli.evaluate.bench.common import REPO, Metered, run_metered, run_process, run_track, write_queries
from condtrack_cli.evaluate.bench.versus_lk import PAPER_CONFIG, versus_lk_queries
from condtrack_cli.evaluate.groundtruth import load_gt_csv


#: Methods of the speed comparison with OpenCV LK (issue 13) and of the profile table.
FILTER_METHODS = ("clf", "auto", "cnlf")
SPEED_METHODS = FILTER_METHODS + ("stk",)

#: Rows of the ``paper`` preset in the speed table (issue 29): its CLF only. Its CNLF and auto regress the
#: motion per particle (~0.7 ms a particle and frame: ~35 s a frame on the 500-point scene), far too slow for
#: three rounds here; their whole-run times are in the section against OpenCV LK, beside their accuracy.
PAPER_SPEED_METHODS = ("clf",)

#: Issue 26's targets: the largest whole-process time of each method over the OpenCV script's, same run.
TIME_TARGETS = {"clf": 4.0, "auto": 5.0, "cnlf": 6.0, "stk": 1.3}

#: Suffix of the rows run with ``--forward-only`` where the scene has queries after frame 0: like the OpenCV
#: script, they track each point from its query frame on only (no backward pass), the like-for-like comparison.
FORWARD_ONLY = " --forward-only"

#: The shared clip of the speed comparison on real frames (KITTI, 1242x375).
SPEED_CLIP = "kt3dmoseg_seq005_clip01"

#: Issue 45's bound on a change's speed: its whole-process wall time at most this many times an earlier commit's,
#: in alternated runs on the same machine (:func:`versus_table`).
VERSUS_BOUND = 1.15


def synthetic_speed_scene(work: Path, n_points: int = 500, n_frames: int = 60,
                          size: tuple[int, int] = (640, 480)) -> tuple[str, Path, Path]:
    """(title, frames folder, queries CSV): the synthetic camera_motion scene (seed 1) at ``size``, ``n_frames`` frames.

    ``n_points`` points drawn uniformly (seed 0) at least 24 px from the border on
    frame 0; those that leave the frame or that the scene hides are still asked for.
    """
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    stem = f"speed-{size[0]}x{size[1]}-{n_frames}"
    folder = write_scene(make_scene("camera_motion", seed=1, size=size, n_frames=n_frames), work / "speed" / stem)
    rng = np.random.default_rng(0)
    margin = 24
    xy = np.column_stack([rng.uniform(margin, size[0] - margin, n_points), rng.uniform(margin, size[1] - margin, n_points)])
    queries = work / f"{stem}.queries.csv"
    write_queries(np.column_stack([np.arange(n_points), np.zeros(n_points), xy]), queries)
    return f"synthetic camera_motion {size[0]}x{size[1]}, {n_frames} frames, {n_points} points", folder, queries


def speed_scenes(work: Path, shared: Path) -> list[tuple[str, Path, Path]]:
    """(title, frames folder, queries CSV) of the speed cases of issue 13.

    :func:`synthetic_speed_scene` at its defaults (640 x 480, 60 frames, 500 points),
    and the first 20 frames of the shared ``SPEED_CLIP`` with the real-video queries
    of issue 11 (:func:`versus_lk_queries`) on them, when the shared data is there.
    """
    scenes = [synthetic_speed_scene(work)]
    clip = shared / SPEED_CLIP
    if (clip / "tracks.csv").is_file():
        rows = versus_lk_queries(load_gt_csv(clip / "tracks.csv"), oxford=False)
        kitti = work / "speed_kitti.queries.csv"
        write_queries(rows, kitti)
        n_clip = len(list(clip.glob("*.png")))
        scenes.append((f"{SPEED_CLIP} 1242x375, {n_clip} frames, {len(rows)} points", clip, kitti))
    return scenes


def run_plain_lk(folder: Path, queries: Path, out: Path, threads: int | None = None) -> tuple[float, float, int, str]:
    """Run the plain OpenCV script (``plain_lk.py``) as its own process: like :func:`run_track`."""
    script = Path(__file__).resolve().parents[1] / "plain_lk.py"
    return run_process([sys.executable, str(script), str(folder), str(queries), str(out)]
                       + ([str(threads)] if threads else []))


def compile_package(package: Path = REPO / "condtrack_cli") -> None:
    """Write the bytecode of the ``condtrack_cli`` folder ``package`` (this one) beside its sources, as pip does when
    it installs a package.

    Where ``PYTHONDONTWRITEBYTECODE`` is set (as on the machines this benchmark was
    first run on), every ``condtrack track`` would otherwise compile the package's
    modules again at each start (bench/results.md, "Speed"), while the OpenCV
    script's imports (numpy, OpenCV) read their installed bytecode.
    """
    compileall.compile_dir(str(package), quiet=1)


def speed_table(work: Path, shared: Path, repeats: int = 3, threads: int | None = None) -> list[str]:
    """Markdown: whole-process wall time of each method over the plain OpenCV LK script's, per speed scene (issue 26).

    Per scene, ``repeats`` rounds each run the script (``plain_lk.py``: decode, LK
    with the forward-backward check, CSV out) then each of ``SPEED_METHODS`` (``condtrack
    track``, start-up and writing the CSV file included, as the script and issue 26's protocol do), one
    process each; the table gives the median wall time, its ratio to the script's median of the same
    run, the largest peak RSS and issue 26's check. Where the scene's queries span
    several frames, each method runs again with ``--forward-only`` (rows from the query
    frame on, as the script writes). ``threads``: both sides pinned
    to that many threads (``--threads`` and ``cv2.setNumThreads``); None: their defaults.
    """
    paper = tuple(f"paper {m}" for m in PAPER_SPEED_METHODS)
    pinned = [] if threads is None else ["--threads", str(threads)]
    compile_package()
    lines = [
        f"Whole-process wall time, median of {repeats} rounds run one after the other (script, then each method), "
        "and its ratio to the plain OpenCV LK script (`condtrack_cli/evaluate/plain_lk.py`: calcOpticalFlowPyrLK "
        "winSize 21, maxLevel 3, forward-backward check 1 px, CSV out) of the same run"
        + (f", both pinned to {threads} thread(s)" if threads else ", each with its default threads") + ". "
        "condtrack writes CSV, as the script does. Issue 26's targets: "
        + ", ".join(f"{m} <= {x:g}x" for m, x in TIME_TARGETS.items()) + ", peak RSS <= 300 MiB. "
        f"Rows `METHOD{FORWARD_ONLY}` (scenes whose queries span several frames): condtrack without its backward "
        "pass, rows from each query frame on only, as the script writes them.",
        "",
    ]
    for title, folder, queries in speed_scenes(work, shared):
        spans = np.loadtxt(queries, delimiter=",", skiprows=1, ndmin=2)[:, 1].max() > 0
        forward_only = tuple(m + FORWARD_ONLY for m in SPEED_METHODS) if spans else ()
        methods = ("opencv-lk",) + SPEED_METHODS + forward_only + paper
        times, peaks, failed = {m: [] for m in methods}, {m: 0.0 for m in methods}, {}
        for _ in range(repeats):
            for method in methods:
                if method == "opencv-lk":
                    seconds, rss, code, message = run_plain_lk(folder, queries, work / "speed.lk.csv", threads)
                elif method.startswith("paper "):
                    plain = method.split()[1]
                    seconds, rss, code, message = run_track(
                        [str(folder), "-p", str(queries), "-c", str(PAPER_CONFIG), "-m", plain,
                         "-o", str(work / f"speed.paper-{plain}.csv")] + pinned)
                else:
                    plain = method.removesuffix(FORWARD_ONLY)
                    seconds, rss, code, message = run_track(
                        [str(folder), "-p", str(queries), "-m", plain, "-o", str(work / f"speed.{plain}.csv")] + pinned
                        + (["--forward-only"] if method.endswith(FORWARD_ONLY) else []))
                if code:
                    failed[method] = message
                times[method].append(seconds)
                peaks[method] = max(peaks[method], rss)
        lk = float(np.median(times["opencv-lk"]))
        lines += [f"Scene: {title}.", "", "| method | wall (s) | × OpenCV LK | peak RSS (MiB) | check |",
                  "|---|---|---|---|---|"]
        for method in methods:
            if method in failed:
                lines.append(f"| {method} | failed: {failed[method]} | | | |")
                continue
            median = float(np.median(times[method]))
            target = TIME_TARGETS.get(method.removesuffix(FORWARD_ONLY))
            check = "" if target is None else ("pass" if median / lk <= target else "FAIL") + f" (<= {target:g}x)"
            lines.append(f"| {method} | {median:.2f} | {median / lk:.1f} | {peaks[method]:.0f} | {check} |")
            print(lines[-1], file=sys.stderr)
        lines.append("")
    return lines


def frame_zero_scenes(work: Path, shared: Path) -> list[tuple[str, Path, Path]]:
    """:func:`speed_scenes` with the queries at frame 0 only (issue 45 judges its speed bound so): a scene whose
    queries span several frames gets a queries CSV of those at frame 0 beside its own."""
    scenes = []
    for title, folder, queries in speed_scenes(work, shared):
        rows = np.loadtxt(queries, delimiter=",", skiprows=1, ndmin=2)
        at_zero = rows[rows[:, 1] == 0]
        if len(at_zero) < len(rows):
            queries = queries.with_name(queries.name.removesuffix(".csv") + ".frame0.csv")
            write_queries(at_zero, queries)
            title += f", the {len(at_zero)} at frame 0"
        scenes.append((title, folder, queries))
    return scenes


def extract_revision(revision: str, work: Path) -> tuple[str, Path]:
    """(short hash, folder) of commit ``revision``'s ``condtrack_cli`` package, taken from this checkout's git history
    into a folder of ``work`` (``folder / "condtrack_cli"``) and compiled as :func:`compile_package` does.
    SystemExit with a one-line ``Error:`` where git is missing or ``revision`` names no commit of this checkout."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, check=True)

    try:
        commit = git("rev-parse", "--verify", "--quiet", f"{revision}^{{commit}}").stdout.decode().strip()
        archive = git("archive", "--format=tar", commit, "condtrack_cli").stdout
    except FileNotFoundError:
        raise SystemExit("Error: --speed-versus: git was not found (it reads the commit from this checkout)") from None
    except subprocess.CalledProcessError:
        raise SystemExit(f"Error: --speed-versus {revision!r}: no such commit with a condtrack_cli package in "
                         f"{REPO}'s git history") from None
    folder = work / f"versus-{commit[:12]}"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        if hasattr(tarfile, "data_filter"):  # Python >= 3.11.4 (3.12 warns without a filter)
            tar.extractall(folder, filter="data")
        else:
            tar.extractall(folder)
    compile_package(folder / "condtrack_cli")
    return commit[:12], folder


def versus_row(method: str, earlier: list[Metered], this: list[Metered], lk_seconds: float) -> str:
    """Markdown row of :func:`versus_table` for ``method`` from the rounds' runs of the earlier commit and of this
    tree (the same rounds, in order) and the OpenCV script's median wall time (s) of the same rounds: the median
    wall times, the median of the rounds' ratios (this / earlier; min-max), the median ratio of their CPU times,
    both trees' ratio to the script, and the check of ``VERSUS_BOUND`` on the median of the rounds' ratios."""
    wall = [b.seconds / a.seconds for a, b in zip(earlier, this)]
    cpu = [b.cpu_seconds / a.cpu_seconds for a, b in zip(earlier, this)]
    before, after = np.median([a.seconds for a in earlier]), np.median([b.seconds for b in this])
    ratio = float(np.median(wall))
    check = ("pass" if ratio <= VERSUS_BOUND else "FAIL") + f" (<= {VERSUS_BOUND:g}x)"
    return (f"| {method} | {before:.2f} | {after:.2f} | {ratio:.3f} ({min(wall):.2f}-{max(wall):.2f}) "
            f"| {np.median(cpu):.3f} | {before / lk_seconds:.2f} / {after / lk_seconds:.2f} | {check} |")


def versus_table(work: Path, shared: Path, revision: str, rounds: int = 5) -> list[str]:
    """Markdown: this tree's methods against commit ``revision``'s (issue 45's speed bound), whole processes.

    Per scene of :func:`frame_zero_scenes`, ``rounds`` rounds each run the OpenCV script (``plain_lk.py``), then
    each of ``SPEED_METHODS`` with both packages back to back (``condtrack track`` with ``PYTHONPATH`` on the
    package, from ``work``: the earlier commit's first in odd rounds, this tree's first in even ones), each with its
    default threads; the table gives :func:`versus_row` per method. Alternation, and the ratio taken within each
    round, keep a machine whose speed drifts over minutes from tipping the comparison (bench/history.md, "Speed since
    35ed7c7")."""
    label, earlier = extract_revision(revision, work)
    compile_package()
    trees = {label: earlier, "this tree": REPO}
    lines = [
        f"Whole-process wall time of each method in this tree against commit {label}, {rounds} rounds run one after "
        "the other (the plain OpenCV LK script, then each method by both packages back to back, in alternating "
        "order), each with its default threads, the queries at frame 0; the ratio is taken within each round and "
        f"issue 45's bound is its median <= {VERSUS_BOUND:g}x. CPU: user + system time of the process and its threads.",
        "",
    ]
    for title, folder, queries in frame_zero_scenes(work, shared):
        lk: list[float] = []
        runs: dict[tuple[str, str], list[Metered]] = {(m, t): [] for m in SPEED_METHODS for t in trees}
        for number in range(rounds):
            lk.append(run_plain_lk(folder, queries, work / "versus.lk.csv")[0])
            for method in SPEED_METHODS:
                for tree in list(trees) if number % 2 == 0 else list(trees)[::-1]:
                    metered = run_metered([sys.executable, "-m", "condtrack_cli", "track", str(folder), "-p",
                                           str(queries), "-m", method, "-o", str(work / f"versus.{method}.csv"), "-q"],
                                          env={**os.environ, "PYTHONPATH": str(trees[tree])}, cwd=work)
                    if metered.code:
                        raise SystemExit(f"Error: {method} of {tree} failed on {folder.name}: {metered.message}")
                    runs[method, tree].append(metered)
        lk_seconds = float(np.median(lk))
        lines += [f"Scene: {title}; OpenCV LK script {lk_seconds:.2f} s (median).", "",
                  f"| method | {label} wall (s) | this tree wall (s) | ratio, median of rounds (min-max) | CPU ratio "
                  f"| × OpenCV LK ({label} / this tree) | check |", "|---|---|---|---|---|---|---|"]
        for method in SPEED_METHODS:
            lines.append(versus_row(method, runs[method, label], runs[method, "this tree"], lk_seconds))
            print(lines[-1], file=sys.stderr)
        lines.append("")
    return lines


#: Clip lengths (frames) of the memory table, and the largest growth issue 13 allows from the first to the last.
MEMORY_LENGTHS = (100, 1000)
MEMORY_GROWTH = 1.2


def memory_table(work: Path, methods: tuple[str, ...] = FILTER_METHODS) -> list[str]:
    """Markdown: peak RSS of each method on the 640 x 480 speed scene at each of ``MEMORY_LENGTHS`` frames (issue 13).

    One ``condtrack track`` process per method and length (HDF5 output), measured by
    ``peak.py``; the check is the longest clip's peak over the shortest's, at most
    ``MEMORY_GROWTH``.
    """
    scenes = [synthetic_speed_scene(work, n_frames=length) for length in MEMORY_LENGTHS]
    lines = [
        "Peak RSS (MiB) of one `condtrack track` process (HDF5 output) on the synthetic camera_motion scene at "
        f"640x480 with 500 points, by clip length; issue 13's target: the {MEMORY_LENGTHS[-1]}-frame clip at most "
        f"{MEMORY_GROWTH}x the {MEMORY_LENGTHS[0]}-frame one.",
        "",
        "| method | " + " | ".join(f"{length} frames" for length in MEMORY_LENGTHS) + " | growth | check |",
        "|---|" + "---|" * (len(MEMORY_LENGTHS) + 2),
    ]
    for method in methods:
        peaks = []
        for _, folder, queries in scenes:
            _, rss, code, message = run_track([str(folder), "-p", str(queries), "-m", method,
                                               "-o", str(work / f"memory.{method}.h5")])
            peaks.append(f"failed: {message}" if code else rss)
        if any(isinstance(peak, str) for peak in peaks):
            lines.append(f"| {method} | " + " | ".join(str(peak) for peak in peaks) + " | | |")
            continue
        growth = peaks[-1] / peaks[0]
        verdict = "pass" if growth <= MEMORY_GROWTH else "FAIL"
        lines.append(f"| {method} | " + " | ".join(f"{peak:.0f}" for peak in peaks) + f" | {growth:.2f} | {verdict} |")
        print(lines[-1], file=sys.stderr)
    return lines


#: Stages of the profile table: (name, file suffix, function) whose cumulative time is the stage's;
#: the stages are disjoint (none calls another).
PROFILE_STAGES = (
    ("frame decoding (cv2.imread; a reader thread, which cProfile does not see)", "~", "<imread>"),
    ("pyramids and gradients (pyramid.deepen)", "motion/pyramid.py", "deepen"),
    ("dense field (DIS, dense.DenseFlow.between)", "motion/dense.py", "between"),
    ("global fit to the field (dense.fit_field)", "motion/dense.py", "fit_field"),
    ("global fit's weights and scale (robust.fit_of)", "motion/robust.py", "fit_of"),
    ("Q_k of the local field (dense.window_spread)", "motion/dense.py", "window_spread"),
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
    """Markdown: where the time goes (cProfile of one ``condtrack track --threads 1`` process per method and speed
    scene: the motion stage in the profiled thread)."""
    scenes = speed_scenes(work, shared)
    lines = [
        "Share of one `condtrack track` process's time by stage (cProfile, which slows Python-level code more than "
        "OpenCV/numpy calls), calls = calls of the stage's function, with one thread: with more, the motion "
        "stage runs in a thread of its own, which cProfile does not see. Scenes: "
        + "; ".join(f"({chr(97 + i)}) {title}" for i, (title, _, _) in enumerate(scenes)) + ". "
        "`python -m cProfile -o out.prof -m condtrack_cli track FRAMES -p QUERIES -m METHOD -o out.h5 -q "
        "--threads 1`.",
        "",
        "| stage | " + " | ".join(f"{m} ({chr(97 + i)})" for i in range(len(scenes)) for m in FILTER_METHODS) + " |",
        "|---|" + "---|" * (len(scenes) * len(FILTER_METHODS)),
    ]
    columns = []
    for index, (_, folder, queries) in enumerate(scenes):
        for method in FILTER_METHODS:
            profile = work / f"profile.{index}.{method}.prof"
            subprocess.run([sys.executable, "-m", "cProfile", "-o", str(profile), "-m", "condtrack_cli", "track",
                            str(folder), "-p", str(queries), "-m", method, "-o", str(work / "profile.h5"), "-q",
                            "--threads", "1"],
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
