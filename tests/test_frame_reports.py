"""Per-frame reports kept on disk in blocks (issue 13, memory flat in the clip's length): the arrays come back bit for bit."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

import condtrack_cli as ct
from condtrack_cli import frame_reports
from condtrack_cli.errors import CondtrackError
from condtrack_cli.frame_reports import FIELDS, FrameReports, park
from condtrack_cli.types import FrameEstimate, Queries, Tracks
from conftest import SAMPLES


def random_report(rng: np.random.Generator, n_points: int) -> FrameEstimate:
    """A report with every field filled, NaN and inf included, in the dtypes trackers use."""
    xy = rng.normal(size=(n_points, 2)) * 100
    xy[0] = np.nan
    cov = rng.normal(size=(n_points, 2, 2))
    cov[1] = np.inf
    return FrameEstimate(xy=xy, cov=cov, dof=3.0 + rng.random(n_points), visible=rng.random(n_points) < 0.5, z=rng.normal(size=(n_points, 2)),
                         R=rng.normal(size=(n_points, 2, 2)), method=rng.integers(-1, 3, n_points).astype(np.int8))


@pytest.mark.parametrize("frames", [11, 8])
def test_reports_written_in_blocks_stack_back_bit_for_bit(frames):
    rng = np.random.default_rng(0)
    reports = [random_report(rng, 5) for _ in range(frames)]
    with FrameReports(block_frames=4) as history:  # two blocks on disk, three reports pending or none
        for report in reports:
            history.append(report)
        folder = Path(history._folder.name)
        assert len(list(folder.glob("*.npy"))) == 2 * len(FIELDS)
        assert len(history) == frames and history.last is reports[-1]
        for name in FIELDS:
            expected = np.stack([getattr(r, name) for r in reports], axis=1)
            stacked = history.stack(name)
            assert stacked.dtype == expected.dtype and stacked.shape == expected.shape
            assert stacked.tobytes() == expected.tobytes(), name
    assert not folder.exists()  # close removes the blocks


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
@pytest.mark.parametrize("method", ["clf", "auto"])
def test_a_pass_longer_than_a_block_tracks_as_one_held_in_memory(monkeypatch, shifted_folder, method):
    """6 frames in 4-frame blocks give the same bytes as with every report in memory (auto: the CNLF's path means)."""
    folder, shifts = shifted_folder
    queries = np.array([[0, 100.0, 80.0], [0, 200.0, 150.0], [2, 150.0 + shifts[2, 0], 120.0 + shifts[2, 1]]])
    in_memory = ct.track(folder, queries=queries, method=method).result
    monkeypatch.setattr(frame_reports, "BLOCK_FRAMES", 4)
    saved = []
    save = np.save
    monkeypatch.setattr(np, "save", lambda path, array: (saved.append(path), save(path, array)))
    spilled = ct.track(folder, queries=queries, method=method).result
    # one block of the forward pass (the backward one, frames 2..0, stays in memory), then the forward tracks parked
    assert [Path(path).name for path in saved] == [f"000000.{name}.npy" for name in FIELDS] + [
        f"parked.{name}.npy" for name in FIELDS]
    for name in FIELDS:
        assert getattr(spilled, name).tobytes() == getattr(in_memory, name).tobytes(), name


def test_parked_tracks_are_their_arrays_read_back_from_disk(tmp_path):
    rng = np.random.default_rng(1)
    reports = [random_report(rng, 4) for _ in range(3)]
    queries = Queries(np.arange(4), np.zeros(4, np.int64), rng.normal(size=(4, 2)))
    tracks = Tracks(queries=queries, **{name: np.stack([getattr(r, name) for r in reports], axis=1) for name in FIELDS})
    parked = park(tracks, tmp_path)
    for name in FIELDS:
        array = getattr(parked, name)
        assert isinstance(array, np.memmap) and not array.flags.writeable
        assert array.dtype == getattr(tracks, name).dtype and array.tobytes() == getattr(tracks, name).tobytes()
    assert parked.queries is tracks.queries


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_an_unwritable_temporary_folder_is_a_one_line_error(monkeypatch, tmp_path, shifted_folder):
    folder, _ = shifted_folder
    missing = tmp_path / "no-such-folder"
    monkeypatch.setattr(tempfile, "tempdir", str(missing))
    monkeypatch.setattr(frame_reports, "BLOCK_FRAMES", 2)
    with pytest.raises(CondtrackError, match=f"temporary folder {missing}: cannot write the per-frame results"):
        ct.track(folder, queries=np.array([[0, 100.0, 80.0]]), method="clf")


def test_stacking_no_report_is_an_error():
    with FrameReports() as history, pytest.raises(ValueError, match="no frame"):
        history.stack("xy")


def test_a_run_removes_the_temporary_folders_of_dead_processes(tmp_path):
    """Issue 28.17: a run killed with SIGKILL left its condtrack-* blocks in TMPDIR for good."""
    dead = subprocess.Popen(["true"])
    dead.wait()
    host = socket.gethostname()
    stale, running = tmp_path / f"condtrack-{host}-{dead.pid}-x1", tmp_path / f"condtrack-{host}-{os.getpid()}-x2"
    for folder in (stale, running):
        folder.mkdir()
        (folder / "000000.xy.npy").write_bytes(b"block")
    sample = SAMPLES / "occlusion"  # queries up to frame 7: the forward pass waits on disk (park)
    result = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(sample),
                             "-p", str(sample / "queries.csv"), "-m", "stk", "-q"],
                            capture_output=True, text=True, timeout=120, env={**os.environ, "TMPDIR": str(tmp_path)})
    assert result.returncode == 0, result.stderr
    assert [p.name for p in tmp_path.iterdir()] == [running.name]
