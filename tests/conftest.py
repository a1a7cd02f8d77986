"""Shared fixtures: real photographs shipped with the package, and paths to shared data."""

from __future__ import annotations

from pathlib import Path

import cv2
import signal

import numpy as np
import pytest
from scipy import ndimage

REPO = Path(__file__).resolve().parents[1]
ASSETS = REPO / "condtrack_cli" / "frames" / "assets"
SAMPLES = REPO / "sample_sequences"
SHARED_DATA = REPO.parent / "shared" / "data"
#: Environment under which rich (and so the progress bar) takes stderr for an interactive terminal.
FORCED_TERMINAL = {"TTY_COMPATIBLE": "1", "TTY_INTERACTIVE": "1", "TERM": "xterm", "COLUMNS": "120"}


def load_asset(name: str) -> np.ndarray:
    """(H, W) uint8 grey photograph from the package assets."""
    image = cv2.imread(str(ASSETS / name), cv2.IMREAD_GRAYSCALE)
    assert image is not None, name
    return image


@pytest.fixture
def photo() -> np.ndarray:
    return load_asset("camera.png")


def shared_sequence(name: str) -> Path:
    """Path of a ``../shared/data`` sequence, or skip the test with a message when absent."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.skip(f"shared data {path} is absent")
    return path


def translate(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``image`` moved by (dx, dy) px (content at x goes to x + dx), bilinear, borders reflected."""
    m = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(image, m, image.shape[::-1], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


@pytest.fixture
def shifted_folder(tmp_path, photo) -> tuple[Path, np.ndarray]:
    """A folder of 6 frames of the photo moving by (1.5, -0.75) px per frame; returns (folder, shifts (F, 2))."""
    folder = tmp_path / "frames"
    folder.mkdir()
    shifts = np.array([[1.5 * k, -0.75 * k] for k in range(6)])
    crop = photo[96:352, 96:416]
    for k, (dx, dy) in enumerate(shifts):
        cv2.imwrite(str(folder / f"f{k}.png"), translate(crop, dx, dy))
    return folder, shifts


def sample_inputs(name: str):
    """(frame source, queries, ground truth) of a shipped sample sequence."""
    from condtrack_cli.evaluate.groundtruth import load_gt_csv
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.queries import read_queries

    folder = SAMPLES / name
    source = open_frames(FrameSettings(), folder)
    return source, read_queries(folder / "queries.csv", source.info), load_gt_csv(folder / "tracks.csv")


def render_pair(image: np.ndarray, field, side: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(prev, cur) float32 ``side`` x ``side`` crops from the centre of ``image`` with prev(x) = cur(x + field(x)).

    Both frames are sampled by cubic B-spline (not an estimator's bilinear
    interpolation) and get Gaussian noise of std ``noise`` grey levels, rounded
    and clipped to 8-bit levels, as a camera would give them. ``field`` maps
    (N, 2) crop positions to (N, 2) displacements (px).
    """
    offset = (np.array(image.shape[::-1]) - side) / 2  # (x, y) of the crop's corner
    ys, xs = np.mgrid[0:side, 0:side]
    pixels = np.column_stack((xs.ravel(), ys.ravel())).astype(np.float64) + offset
    rng = np.random.default_rng(seed)
    frames = []
    for positions in (pixels + field(pixels - offset), pixels):
        sampled = ndimage.map_coordinates(image, positions[:, ::-1].T, order=3).reshape(side, side)
        frames.append(np.clip(np.round(sampled + rng.normal(0, noise, sampled.shape)), 0, 255).astype(np.float32))
    return frames[0], frames[1]


def default_sigint() -> None:
    """``preexec_fn`` for a child that is sent Ctrl-C: a test run started as a background job
    (``make test &``) inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
