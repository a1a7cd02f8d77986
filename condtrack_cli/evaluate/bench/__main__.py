"""The benchmark: every method on every sequence with ground truth, plus a speed case.

``make bench`` runs ``python -m condtrack_cli.evaluate.bench --out bench/results.md``.
Each method runs as its own ``condtrack track`` process (whole-process wall time
and peak resident memory, read by the meter ``peak.py``), and is scored with the same
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
``--speed`` only the speed comparison and the profile; ``--memory`` only the
peak memory by clip length (``memory_table``). ``--speed-versus COMMIT`` prints only
this tree's whole-process times against an earlier commit's, in alternated rounds
(``versus_table``: issue 45's speed bound, ``--rounds`` of them).

``--versus-lk`` prints only the section against OpenCV LK and chained DIS (issues 11 and 45), with its
per-group tables; ``--methods`` and ``--sets`` narrow it to some columns and sets (a quick subset),
``--nonrigid tune`` puts the nonrigid scene's tuning seeds in its synthetic table instead of the reporting ones.

``--hard tune|report`` prints only issue 31's hard cases (``hard.py``) on the tuning
or the reporting seeds.

The full run rewrites ``--out`` but keeps the sections of the existing file it does not write
(``other_sections``: the narrower runs pasted in, such as ``--hard report``), after its own.

``--support SEQUENCE`` prints instead the dominant model's one-step prediction
error by neighbourhood support (the measurement behind ``auto``'s thresholds),
then the one-step error of the dominant model and of the local field with and
without its block-matching start.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

from condtrack_cli.evaluate.bench.accuracy import accuracy_table, calibration_table, support_table
from condtrack_cli.evaluate.bench.common import REPO
from condtrack_cli.evaluate.bench.hard import REPORT_SEEDS, TUNE_SEEDS, hard_cases_table
from condtrack_cli.evaluate.bench.seeds import seed_spread_table
from condtrack_cli.evaluate.bench.speed import batch_table, memory_table, profile_table, speed_table, versus_table
from condtrack_cli.evaluate.bench.versus_lk import (
    COLUMNS, NONRIGID_REPORT_SEEDS, NONRIGID_TUNE_SEEDS, PAPER_METHODS, versus_lk_section,
)
from condtrack_cli.progress import show_warnings


#: The titles (a ``## `` heading up to any " (") of the sections the full run writes.
WRITTEN_SECTIONS = ("Accuracy", "Covariance calibration", "Speed", "Profile", "Memory by clip length", "Many clips",
                    "Against OpenCV LK and chained DIS")
#: What bench/results.md holds, under its title.
INTRO = [
    "Today's results, one section per part of the benchmark, each naming the command that wrote its tables and the",
    "commit they were measured at. `make bench` (`python -m condtrack_cli.evaluate.bench --out bench/results.md`) writes",
    "the sections Accuracy, Covariance calibration, Speed, Profile, Memory by clip length, Many clips and Against",
    "OpenCV LK and chained DIS at one commit, and keeps the other sections of this file (the narrower runs pasted in: Calibration,",
    "Student-t; Seed spread; Hard cases; The paper preset). The sections below were measured at different commits, "
    "each given.",
    "Earlier measurements and the ideas tried and not kept: `bench/history.md`, by the same section titles.",
]


def other_sections(text: str) -> list[str]:
    """The lines of ``text``'s ``## `` sections that the full run does not write (WRITTEN_SECTIONS), in order."""
    kept: list[str] = []
    keeping = False
    for line in text.splitlines():
        if line.startswith("## "):
            keeping = line[3:].split(" (")[0].strip() not in WRITTEN_SECTIONS
        if keeping:
            kept.append(line)
    return kept


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
    show_warnings(True)  # library warnings as the command line's ``warning: ...`` lines
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "bench" / "results.md")
    parser.add_argument("--max-points", type=int, default=1000, help="most query points per shared sequence")
    parser.add_argument("--work", type=Path, default=REPO / "bench" / "out",
                        help="folder for the queries and track files (emptied first; kept for `condtrack eval`)")
    parser.add_argument("--support", type=Path, metavar="SEQUENCE",
                        help="only print the motions' one-step errors on SEQUENCE (with tracks.csv)")
    parser.add_argument("--batch", action="store_true", help="only print the batch throughput table")
    parser.add_argument("--speed", action="store_true",
                        help="only print the speed comparison with OpenCV LK and the profile table (issue 13)")
    parser.add_argument("--speed-versus", metavar="COMMIT",
                        help="only print this tree's whole-process times against COMMIT's (a commit of this checkout), "
                             "alternated (issue 45's speed bound)")
    parser.add_argument("--rounds", type=int, default=5, help="with --speed-versus: the rounds (5)")
    parser.add_argument("--memory", action="store_true",
                        help="only print the peak memory of each method by clip length (issue 13)")
    parser.add_argument("--shared-data", type=Path, default=REPO.parent / "shared" / "data",
                        help="folder of the real sets for the section against OpenCV LK")
    parser.add_argument("--versus-lk", action="store_true",
                        help="only print the section against OpenCV LK (issue 11); results.md is not written")
    parser.add_argument("--seeds", type=int, metavar="N",
                        help="only print auto's and cnlf's <δ_avg on the real sets at seeds 0 .. N-1 (mean, min-max), "
                             "LK, chained DIS and clf once, and issue 45's real-video checks and calibration bands on "
                             "the means")
    parser.add_argument("--hard", choices=("tune", "report"),
                        help="only print issue 31's hard cases on the tuning or the reporting seeds")
    parser.add_argument("--paper", default=",".join(PAPER_METHODS), metavar="METHODS",
                        help="with --versus-lk: methods run with configs/paper.yaml as extra columns, comma-separated "
                             "(issue 29; '' for none)")
    parser.add_argument("--lk-points", type=int, default=300,
                        help="with --versus-lk or --seeds: most queries per real set (300; fewer to bound the paper "
                             "preset's time)")
    parser.add_argument("--no-synthetic", action="store_true", help="with --versus-lk: the real sets only")
    parser.add_argument("--methods", default=",".join(COLUMNS), metavar="METHODS",
                        help=f"with --versus-lk: the columns to run, comma-separated among {','.join(COLUMNS)} (all)")
    parser.add_argument("--sets", metavar="GLOBS",
                        help="with --versus-lk or --seeds: only the real sets and synthetic scenes whose names match "
                             "one of these comma-separated globs (e.g. 'dudek_*,nonrigid_*')")
    parser.add_argument("--nonrigid", choices=("tune", "report"), default="report",
                        help="with --versus-lk: the nonrigid scene's tuning or reporting seeds in the synthetic table")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="with --versus-lk, --seeds or --hard: a config override for every condtrack run (a "
                             "variant's numbers)")
    args = parser.parse_args()
    extra = tuple(arg for override in args.set for arg in ("--set", override))  # every condtrack run's overrides
    sets = tuple(pattern for pattern in args.sets.split(",") if pattern) if args.sets else None
    if args.hard:
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(hard_cases_table(args.work, TUNE_SEEDS if args.hard == "tune" else REPORT_SEEDS, extra)))
        return
    if args.seeds is not None:
        if args.seeds < 1:
            parser.error(f"--seeds: expected a positive integer, got {args.seeds}")
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(seed_spread_table(args.work, args.shared_data, args.seeds, extra, sets, args.lk_points)))
        return
    if args.versus_lk:
        args.work.mkdir(parents=True, exist_ok=True)
        paper = tuple(method for method in args.paper.split(",") if method)
        methods = tuple(method for method in args.methods.split(",") if method)
        unknown = [method for method in methods if method not in COLUMNS]
        if unknown:
            parser.error(f"--methods: unknown column {unknown[0]!r}; valid: {', '.join(COLUMNS)}")
        seeds = NONRIGID_TUNE_SEEDS if args.nonrigid == "tune" else NONRIGID_REPORT_SEEDS
        print("\n".join(versus_lk_section(args.work, args.shared_data, extra, paper, args.lk_points,
                                          not args.no_synthetic, methods, sets, seeds)))
        return
    if args.support:
        print("\n".join(support_table(args.support)))
        return
    if args.speed:
        shutil.rmtree(args.work / "speed", ignore_errors=True)
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(speed_table(args.work, args.shared_data) + ["One thread:", ""]
                        + speed_table(args.work, args.shared_data, threads=1) + ["## Profile", ""]
                        + profile_table(args.work, args.shared_data)))
        return
    if args.speed_versus:
        if args.rounds < 1:
            parser.error(f"--rounds: expected a positive integer, got {args.rounds}")
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(versus_table(args.work, args.shared_data, args.speed_versus, args.rounds)))
        return
    if args.memory:
        shutil.rmtree(args.work / "speed", ignore_errors=True)
        args.work.mkdir(parents=True, exist_ok=True)
        print("\n".join(memory_table(args.work)))
        return
    if args.batch:
        shutil.rmtree(args.work / "batch", ignore_errors=True)
        print("\n".join(batch_table(args.work)))
        return
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    accuracy = accuracy_table(args.max_points, args.work)
    speed = speed_table(args.work, args.shared_data) + ["One thread:", ""] + speed_table(args.work, args.shared_data,
                                                                                             threads=1)
    profile = profile_table(args.work, args.shared_data)
    memory = memory_table(args.work)
    batch = batch_table(args.work)
    versus_lk = versus_lk_section(args.work, args.shared_data)
    header = [
        "# condtrack benchmark",
        "",
        *INTRO,
        "",
        "## Accuracy (TAP-Vid 'first' query mode; shared sets: queries = first observation of tracks "
        f"with >= 3 observations, at most {args.max_points} per sequence)",
        "",
        f"- date: {datetime.date.today().isoformat()}",
        f"- machine: {machine()}",
        f"- commit: {commit()}",
        "- command: `make bench`",
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
    kept = other_sections(args.out.read_text(encoding="utf-8")) if args.out.is_file() else []
    text = "\n".join(header + accuracy + calibration + ["", "## Speed (issue 13)", ""] + speed + ["## Profile", ""] + profile + ["", "## Memory by clip length", ""] + memory + ["", "## Many clips", ""] + batch + [""] + versus_lk + ([""] + kept if kept else [])).rstrip("\n") + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"bench: wrote {args.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
