"""The per-frame reports of one tracking pass, kept on disk in blocks so that memory stays flat in the clip's length.

A tracker reports a :class:`FrameEstimate` for all P points on every frame: xy,
cov, visible, z, R and method, 98 bytes a point and frame (49 MB for 500 points
over 1000 frames). Held in a list they grew with the clip while the motion
stage's work arrays were alive, which set the peak memory of a long clip. Here
every ``block_frames`` reports are stacked into (P, block, ...) arrays and written
as ``.npy`` files to a temporary folder (``tempfile``: ``TMPDIR``), and read back
only when the tracker stacks the whole pass (``Tracker.finish``), after the
pipeline has let the motion stage's work arrays go. The arrays read back are
the arrays reported, bit for bit. A folder that cannot be written is a
:class:`CondtrackError` naming it.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from condtrack_cli.errors import CondtrackError
from condtrack_cli.types import FrameEstimate

#: The fields of a report, each (P, ...) per frame.
FIELDS = ("xy", "cov", "visible", "z", "R", "method")

#: Reports stacked into one block on disk (500 points: 3 MB a block).
BLOCK_FRAMES = 64


class FrameReports:
    """The reports of frames 0, 1, ... of one pass, in order; ``close`` removes the blocks on disk.

    Usable as a context manager. ``last`` is the latest report (None before the first).
    """

    def __init__(self, block_frames: int | None = None):
        self.block_frames = BLOCK_FRAMES if block_frames is None else block_frames
        self.last: FrameEstimate | None = None
        self._pending: list[FrameEstimate] = []  # reports not yet written, at most block_frames - 1
        self._blocks: list[int] = []  # frames in each block written, in order
        self._folder: tempfile.TemporaryDirectory | None = None  # made at the first block written

    def __enter__(self) -> "FrameReports":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def __len__(self) -> int:
        return sum(self._blocks) + len(self._pending)

    def append(self, report: FrameEstimate) -> None:
        """Add the next frame's report; every ``block_frames`` reports go to disk as one block."""
        self._pending.append(report)
        self.last = report
        if len(self._pending) == self.block_frames:
            try:
                if self._folder is None:
                    self._folder = tempfile.TemporaryDirectory(prefix="condtrack-reports-")
                for name in FIELDS:
                    np.save(self._path(len(self._blocks), name), self._stack_pending(name))
            except OSError as error:
                raise CondtrackError(
                    f"temporary folder {tempfile.gettempdir()}: cannot write the per-frame results "
                    f"({error.strerror or error}); set TMPDIR to a writable folder with space") from error
            self._blocks.append(len(self._pending))
            self._pending = []

    def stack(self, name: str) -> np.ndarray:
        """(P, F, ...) the field ``name`` of every report, frame after frame (F = ``len(self)``)."""
        if not len(self):
            raise ValueError("no frame was reported")
        sample = getattr(self.last, name)
        out = np.empty((sample.shape[0], len(self)) + sample.shape[1:], sample.dtype)
        start = 0
        for block, frames in enumerate(self._blocks):
            out[:, start : start + frames] = np.load(self._path(block, name))
            start += frames
        if self._pending:
            out[:, start:] = self._stack_pending(name)
        return out

    def close(self) -> None:
        """Remove the blocks written to disk (the reports are gone after this)."""
        if self._folder is not None:
            self._folder.cleanup()
            self._folder = None
        self._blocks, self._pending, self.last = [], [], None

    def _stack_pending(self, name: str) -> np.ndarray:
        return np.stack([getattr(report, name) for report in self._pending], axis=1)

    def _path(self, block: int, name: str) -> Path:
        return Path(self._folder.name) / f"{block:06d}.{name}.npy"
