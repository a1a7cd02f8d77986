"""Real signals to a real ``condtrack track`` while it writes its outputs (issue 16 items 3, 4).

A run interrupted by Ctrl-C (SIGINT) or SIGTERM exits 130 or 143 with one
``Error: interrupted`` line, publishes no output after the signal (a file
already published before it stays whole), and leaves no ``*.part`` file.

To hit the HDF5 write and the overlay render, the clip carries 30 000 query
points (the HDF5 file is about 8 MB and its write lasts about a second of CPU
time, the render several). The HDF5 signal is sent once the temporary
``.part`` file holds 100 kB, that is while h5py writes datasets: a signal
there used to be swallowed by h5py (printed as "Exception ignored", the file
published, exit 0). The overlay signal is sent as soon as its temporary
``.part`` folder appears; the HDF5 file, written by then into its own staging folder, is not published either.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
from conftest import default_sigint


N_POINTS = 30_000


@pytest.fixture(scope="module")
def many_points(tmp_path_factory):
    """(frame folder, queries CSV): 6 frames of 64 x 64 px, 30 000 queries on frame 0."""
    root = tmp_path_factory.mktemp("many_points")
    folder = root / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 256, (64, 64)).astype(np.uint8), (0, 0), 2)
    for k in range(6):
        cv2.imwrite(str(folder / f"{k}.png"), np.roll(texture, k, axis=1))
    queries = root / "queries.csv"
    xy = rng.uniform(5, 58, (N_POINTS, 2))
    queries.write_text("frame,x,y\n" + "".join(f"0,{x:.3f},{y:.3f}\n" for x, y in xy))
    return folder, queries


def _size(paths: list) -> int:
    """Bytes of the first of ``paths`` (-1 when there is none or it just vanished)."""
    try:
        return paths[0].stat().st_size if paths else -1
    except FileNotFoundError:
        return -1


def _interrupt_when(pattern: str, min_bytes: int, out_dir, args: list[str], signum: int) -> subprocess.CompletedProcess:
    """Run ``condtrack track``; send ``signum`` once a file matching ``pattern`` in ``out_dir`` has ``min_bytes``."""
    process = subprocess.Popen([sys.executable, "-m", "condtrack_cli", "track", *args, "-q"],
                               stdout=subprocess.PIPE, preexec_fn=default_sigint, stderr=subprocess.PIPE, text=True)
    while _size(list(out_dir.glob(pattern))) < min_bytes:
        assert process.poll() is None, f"the run ended before {pattern} had {min_bytes} bytes: {process.stderr.read()}"
        time.sleep(0.002)
    process.send_signal(signum)
    stdout, stderr = process.communicate(timeout=300)
    return subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr)


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_during_the_hdf5_write(many_points, tmp_path, signum, code):
    folder, queries = many_points
    out = tmp_path / "out.h5"
    result = _interrupt_when(".out.h5.*.part", 100_000, tmp_path, [str(folder), "-p", str(queries), "-m", "mdr", "-o", str(out)],
                             signum)
    assert result.returncode == code, result.stderr
    assert result.stderr == "Error: interrupted\n"  # issue 47.16: no blank line first off a terminal
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_during_the_overlay_render(many_points, tmp_path, signum, code):
    folder, queries = many_points
    out, overlay = tmp_path / "out.h5", tmp_path / "out.mp4"
    args = [str(folder), "-p", str(queries), "-m", "mdr", "-o", str(out), "--overlay", str(overlay)]
    result = _interrupt_when(".out.mp4.*.part", 0, tmp_path, args, signum)
    assert result.returncode == code, result.stderr
    assert result.stderr == "Error: interrupted\n"  # issue 47.16: no blank line first off a terminal
    assert list(tmp_path.iterdir()) == []  # the .h5 is published with the overlay, not before it
