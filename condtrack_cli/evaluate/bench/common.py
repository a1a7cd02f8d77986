"""Helpers shared by the benchmark sections: queries from ground truth, one timed ``condtrack track`` process, the sequences."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import NamedTuple

import numpy as np

from condtrack_cli.evaluate.groundtruth import GroundTruth, load_gt_csv

REPO = Path(__file__).resolve().parents[3]

#: The meter that times a command and reads its peak memory.
METER = Path(__file__).resolve().with_name("peak.py")


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


class Metered(NamedTuple):
    """What the meter ``peak.py`` read of one command."""

    seconds: float  #: wall time (s)
    cpu_seconds: float  #: user + system CPU time of the command and its threads (s)
    peak_mib: float  #: peak resident memory (MiB)
    code: int  #: exit code
    message: str  #: stderr's last line


def run_metered(command: list[str], env: dict[str, str] | None = None, cwd: Path | None = None) -> Metered:
    """Run ``command`` (stdout discarded) under the meter ``peak.py``, a standard-library process that times it and
    reads its peak RSS: read here, the peak would include this benchmark's own memory at the fork (see ``peak.py``).
    env: the command's whole environment (None: this process's); cwd: its working folder (None: this one's)."""
    with tempfile.TemporaryDirectory() as folder:
        result = Path(folder) / "peak.json"
        process = subprocess.run([sys.executable, "-I", str(METER), str(result), *command],
                                 stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, env=env, cwd=cwd)
        measured = json.loads(result.read_text())
    stderr = process.stderr.decode()
    return Metered(measured["seconds"], measured["cpu_seconds"], measured["peak_mib"], process.returncode,
                   (stderr.strip().splitlines() or [""])[-1])


def run_process(command: list[str]) -> tuple[float, float, int, str]:
    """Run ``command``: (wall seconds, peak RSS MiB, exit code, stderr's last line) of :func:`run_metered`."""
    metered = run_metered(command)
    return metered.seconds, metered.peak_mib, metered.code, metered.message


def run_track(args: list[str]) -> tuple[float, float, int, str]:
    """Run ``condtrack track ARGS -q`` as its own process: see :func:`run_process`."""
    return run_process([sys.executable, "-m", "condtrack_cli", "track", *args, "-q"])


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


def fmt(value) -> str:
    return "n/a" if value is None else f"{value:.3f}"
