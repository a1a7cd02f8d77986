"""Per-frame reports kept on disk in blocks (issue 13, memory flat in the clip's length): the arrays come back bit for bit."""

from __future__ import annotations

import errno
import io
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
from condtrack_cli.frame_reports import FIELDS, FrameReports, FrameStore, park
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


def test_the_store_gives_back_the_kept_frames_last_to_first_bit_for_bit(tmp_path):
    rng = np.random.default_rng(2)
    frames = [rng.integers(0, 256, (5, 7), np.uint8) for _ in range(6)]
    store = FrameStore(tmp_path / "frames.u8", last=3)
    passed = list(store.keeping(iter(frames)))
    assert all(a is b for a, b in zip(passed, frames)) and len(passed) == 6  # the forward pass's frames, untouched
    assert (tmp_path / "frames.u8").stat().st_size == 4 * 5 * 7  # frames 0..3 only
    back = list(store.reversed())
    assert [frame.tobytes() for frame in back] == [frames[k].tobytes() for k in (3, 2, 1, 0)]
    assert all(frame.dtype == np.uint8 and frame.shape == (5, 7) for frame in back)


def test_reading_the_store_before_the_forward_pass_kept_its_frames_is_an_error(tmp_path):
    store = FrameStore(tmp_path / "frames.u8", last=3)
    list(store.keeping(iter([np.zeros((2, 2), np.uint8)] * 2)))
    with pytest.raises(ValueError, match="holds 2 frames, not the 4 up to frame 3"):
        next(store.reversed())


def test_an_error_of_the_frames_passes_through_the_store_unchanged(tmp_path):
    def failing():
        yield np.zeros((2, 2), np.uint8)
        raise OSError(errno.EIO, "Input/output error")

    with pytest.raises(OSError, match="Input/output error"):
        list(FrameStore(tmp_path / "frames.u8", last=3).keeping(failing()))


def test_a_full_disk_while_keeping_the_frames_is_a_one_line_error(monkeypatch):
    class Full(io.BytesIO):
        def write(self, _data):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(frame_reports, "open", lambda *_args: Full(), raising=False)  # the store's file only
    sample = SAMPLES / "occlusion"
    with pytest.raises(CondtrackError, match=r"cannot write the per-frame results \(No space left on device\)"):
        ct.track(sample, queries=sample / "queries.csv", method="stk")


def test_a_two_way_run_on_a_video_decodes_each_frame_once(tmp_path, monkeypatch):
    """The backward pass reads the forward pass's frames back from the temporary folder (``FrameStore``) instead of
    decoding the video again from its start."""
    import cv2

    from condtrack_cli.frames import readers

    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48), False)
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (48, 80), np.uint8), (0, 0), 1.5)
    for k in range(8):
        writer.write(np.ascontiguousarray(texture[:, k : k + 64]))
    writer.release()
    decoded = []
    plain_iter = readers.VideoSource.__iter__

    def counting_iter(self):
        for image in plain_iter(self):
            decoded.append(image)
            yield image

    monkeypatch.setattr(readers.VideoSource, "__iter__", counting_iter)
    two_way = ct.track(video, queries=np.array([[0, 30.0, 20.0], [6, 30.0, 20.0]]), method="clf")
    assert len(decoded) == 1 + 8  # opening the video (its first frame, for the size), then the forward pass
    assert np.isfinite(two_way.xy[1, :6]).all()  # the point queried at frame 6 has its backward rows


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
