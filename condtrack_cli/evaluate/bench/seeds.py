"""The seed spread of the methods that draw particles (issue 45): issue 45's checks judged on the mean over seeds.

The CNLF (and ``auto``, through its CNLF) draws its particles from ``--seed``; the CLF, the STK baseline, OpenCV LK
and chained DIS draw nothing. A face clip has seven points, so one point's fate moves its <δ_avg by up to 0.14, and
the seed alone moved ``auto`` on dudek_01 between 0.786 and 0.841 (seeds 0-5 at dfb4c97, LK 0.838): a check read
at seed 0 alone may pass or fail by chance. This table runs ``auto`` and ``cnlf`` at seeds 0 .. N - 1 and the
deterministic columns once, and judges issue 45's real-video checks and its calibration bands (each group's mean
coverage, each set's) on each set's mean over the seeds: a face clip's 90 % coverage moved between 0.79 and 0.89
with the seed alone (``auto`` on dudek_02, seeds 0-5 at 381a548).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from condtrack_cli.evaluate.bench.common import fmt, write_queries
from condtrack_cli.evaluate.bench.versus_lk import (
    REAL_GROUPS,
    group_tables,
    real_video_checks,
    score_versus_lk,
    selected,
    versus_lk_queries,
)
from condtrack_cli.evaluate.groundtruth import load_gt_csv

#: Methods whose tracks depend on ``--seed`` (the CNLF's particles), run once per seed.
SEEDED_METHODS = ("auto", "cnlf")
#: Columns that draw nothing, run once.
FIXED_COLUMNS = ("lk", "dis", "clf")


def mean_metrics(runs: list[dict]) -> dict:
    """The mean of each metric over ``runs`` (one metrics dict per seed); None where any run has None."""
    return {key: None if any(run[key] is None for run in runs) else float(np.mean([run[key] for run in runs]))
            for key in runs[0]}


def spread_cell(values: list[float]) -> str:
    """'mean (min-max)' of a column's <δ_avg over the seeds."""
    return f"{fmt(float(np.mean(values)))} ({fmt(min(values))}-{fmt(max(values))})"


def seed_spread_table(work: Path, shared: Path, seeds: int, extra: tuple[str, ...] = (),
                      sets: tuple[str, ...] | None = None, max_points: int = 300) -> list[str]:
    """Markdown: per real set of ``shared`` (those matching a glob of ``sets``), <δ_avg of the ``FIXED_COLUMNS`` and
    the mean (min-max) of each of ``SEEDED_METHODS`` over seeds 0 .. ``seeds`` - 1, with the bench's queries
    (:func:`versus_lk_queries`); then issue 45's real-video checks on those means (the camel's cov95 too: the mean
    of its coverage), and the group tables with the calibration bands (:func:`group_tables`) on the means.
    extra: arguments added to every ``condtrack track``. Track files: ``work``/seeds_<set>.s<seed>."""
    columns = FIXED_COLUMNS + SEEDED_METHODS
    lines = [f"<δ_avg; {', '.join(SEEDED_METHODS)}: mean (min-max) over seeds 0-{seeds - 1} "
             f"(`condtrack track --seed S`); {', '.join(FIXED_COLUMNS)}: once (they draw nothing).", "",
             "| set | points | " + " | ".join(columns) + " |", "|---|---|" + "---|" * len(columns)]
    per_set, points = {}, {}
    folders = sorted(shared.glob("*/")) if shared.is_dir() else []
    for folder in [f for f in folders if selected([f.name], sets) and (f / "tracks.csv").is_file()]:
        truth = load_gt_csv(folder / "tracks.csv")
        rows = versus_lk_queries(truth, folder.name.startswith("oxford"), max_points)
        queries = work / f"seeds_{folder.name}.queries.csv"
        write_queries(rows, queries)
        results = score_versus_lk(folder, queries, truth, work, f"seeds_{folder.name}", extra, (), FIXED_COLUMNS)
        drawn = [score_versus_lk(folder, queries, truth, work, f"seeds_{folder.name}.s{seed}",
                                 extra + ("--seed", str(seed)), (), SEEDED_METHODS) for seed in range(seeds)]
        cells = [fmt(results[c][0]["delta_avg"]) if results[c][0] else f"failed: {results[c][1]}"
                 for c in FIXED_COLUMNS]
        for method in SEEDED_METHODS:
            runs = [run[method] for run in drawn]
            failures = [message for metrics, message in runs if metrics is None]  # (None, message) where one failed
            if failures:
                results[method] = (None, failures[0])
                cells.append(f"failed: {failures[0]}")
                continue
            results[method] = (mean_metrics([metrics for metrics, _ in runs]),
                               float(np.mean([seconds for _, seconds in runs])))
            cells.append(spread_cell([metrics["delta_avg"] for metrics, _ in runs]))
        per_set[folder.name], points[folder.name] = results, len(rows)
        lines.append(f"| {folder.name} | {len(rows)} | " + " | ".join(cells) + " |")
        print(lines[-1], file=sys.stderr)
    if not per_set:
        return [f"{shared} holds no set with a tracks.csv" + (f" matching {','.join(sets)}" if sets else "")
                + ": no seed-spread table."]
    checks = real_video_checks(per_set, columns)
    return (lines + ["", "Issue 45's real-video checks on the mean over the seeds:", ""] + checks + ["",
            "The groups on the mean over the seeds (`auto`, `cnlf`; `clf` once):", ""]
            + group_tables(per_set, points, REAL_GROUPS))
