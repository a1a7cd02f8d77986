"""The per-frame reports of one tracking pass, kept on disk in blocks so that memory stays flat in the clip's length.

A tracker reports a :class:`FrameEstimate` for all P points on every frame: xy,
cov, visible, z, R and method, 98 bytes a point and frame (49 MB for 500 points
over 1000 frames). Held in a list they grew with the clip while the motion
stage's work arrays were alive, which set the peak memory of a long clip. Here
every ``block_frames`` reports are stacked into (P, block, ...) arrays and written
as ``.npy`` files to a temporary folder (``tempfile``: ``TMPDIR``), and read back
only when the tracker stacks the whole pass (``Tracker.finish``), after the
pipeline has let the motion stage's work arrays go. The arrays read back are
the arrays reported, bit for bit. A pass's stacked tracks can wait on disk the
same way (``park``) while the other pass runs, and the forward pass's frames up to
the latest query frame wait there for the backward pass (``FrameStore``). A
folder that cannot be written is a :class:`CondtrackError` naming it. A folder's
name holds the host and the process id; the first folder a process makes removes
those of dead processes.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from condtrack_cli.errors import CondtrackError
from condtrack_cli.types import FrameEstimate, Tracks

#: The fields of a report, each (P, ...) per frame.
FIELDS = ("xy", "cov", "dof", "visible", "z", "R", "method")

#: Reports stacked into one block on disk (500 points: 3 MB a block).
BLOCK_FRAMES = 64


def owned_name(stem: str) -> str:
    """``<stem>-<host>-<pid>-``: how the name of a folder this process makes starts, so that a later run can tell a
    dead process's folders (``kill -9`` runs no clean-up) from a running one's (:func:`remove_dead_folders`)."""
    return f"{stem}-{socket.gethostname()}-{os.getpid()}-"


def remove_dead_folders(where: str | Path, stem: str) -> None:
    """Delete the folders in ``where`` whose names start as :func:`owned_name` (``stem``) of a dead process of this
    host; a running process's, and another host's (a shared folder), stay."""
    pattern = re.compile(re.escape(f"{stem}-{socket.gethostname()}-") + r"(\d+)-")
    with os.scandir(where) as entries:
        for entry in entries:
            found = pattern.match(entry.name)
            if found and entry.is_dir(follow_symlinks=False) and not _alive(int(found.group(1))):
                shutil.rmtree(entry.path, ignore_errors=True)


#: The stem of the temporary folders' names (:func:`owned_name`).
TEMPORARY_STEM = "condtrack"


@functools.cache
def remove_stale_folders() -> None:
    """Delete, once per process, the temporary folders left in ``TMPDIR`` by dead condtrack processes of this host."""
    remove_dead_folders(tempfile.gettempdir(), TEMPORARY_STEM)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    return True


def temporary_folder() -> tempfile.TemporaryDirectory:
    """A new temporary folder for arrays waiting on disk; a CondtrackError naming ``TMPDIR``'s folder when it fails."""
    try:
        remove_stale_folders()
        return tempfile.TemporaryDirectory(prefix=owned_name(TEMPORARY_STEM))
    except OSError as error:
        raise _write_error(error) from error


def save(path: Path, array: np.ndarray) -> None:
    """``array`` to the ``.npy`` file ``path``; a CondtrackError when it cannot be written (disk full)."""
    try:
        np.save(path, array)
    except OSError as error:
        raise _write_error(error) from error


def park(tracks: Tracks, folder: Path) -> Tracks:
    """``tracks`` with its (P, F, ...) arrays written to ``folder`` and read back memory-mapped, read-only.

    While a pass's tracks wait for the other pass (``pipeline.run``), their pages are
    the file's, which the system can drop; ``extras`` stay as they are.
    """
    parked = {}
    for name in FIELDS:
        path = folder / f"parked.{name}.npy"
        save(path, getattr(tracks, name))
        parked[name] = np.load(path, mmap_mode="r")
    return dataclasses.replace(tracks, **parked)


def _write_error(error: OSError) -> CondtrackError:
    return CondtrackError(f"temporary folder {tempfile.gettempdir()}: cannot write the per-frame results "
                          f"({error.strerror or error}); set TMPDIR to a writable folder with space")


class FrameStore:
    """Frames 0..``last`` of the forward pass kept as raw bytes in ``path``, read back last to first.

    The backward pass (``pipeline.run``) reads them from here instead of decoding the
    input again: a folder's images and a video (which can only be decoded from its
    start) are decoded once. The file holds (last + 1) H W bytes (plain writes, not a
    memory map: the pages are the system's cache, not the process's memory); the
    frames read back are those decoded, bit for bit.
    """

    def __init__(self, path: Path, last: int):
        self.path = path
        self.last = last
        self._shape: tuple[int, int] | None = None  #: (H, W) of the frames kept
        self._kept = 0

    def keeping(self, frames: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        """``frames`` as they are, frames 0..``last`` (H, W) uint8 written to the store on the way; a CondtrackError
        naming the temporary folder when the store cannot be written (an error of ``frames`` passes unchanged)."""
        try:
            store = open(self.path, "wb")
        except OSError as error:
            raise _write_error(error) from error
        with store:
            for index, frame in enumerate(frames):
                if index <= self.last:
                    try:
                        store.write(np.ascontiguousarray(frame, np.uint8).data)
                    except OSError as error:
                        raise _write_error(error) from error
                    self._shape, self._kept = frame.shape, index + 1
                yield frame

    def reversed(self) -> Iterator[np.ndarray]:
        """Frames ``last``, ``last - 1``, ..., 0 as (H, W) uint8, once ``keeping`` has gone through them."""
        if self._kept != self.last + 1:
            raise ValueError(f"the store holds {self._kept} frames, not the {self.last + 1} up to frame {self.last}")
        size = self._shape[0] * self._shape[1]
        for index in range(self.last, -1, -1):
            yield np.fromfile(self.path, np.uint8, count=size, offset=index * size).reshape(self._shape)


class FrameReports:
    """The reports of frames 0, 1, ... of one pass, in order; ``close`` removes the blocks on disk.

    Usable as a context manager. ``last`` is the latest report (None before the first).
    """

    def __init__(self, block_frames: int | None = None):
        self.block_frames = BLOCK_FRAMES if block_frames is None else block_frames
        self.last: FrameEstimate | None = None
        self._pending: list[FrameEstimate] = []  # reports not yet written, at most block_frames - 1
        self._written = 0  # blocks written, block_frames reports each
        self._folder: tempfile.TemporaryDirectory | None = None  # made at the first block written

    def __enter__(self) -> "FrameReports":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def __len__(self) -> int:
        return self._written * self.block_frames + len(self._pending)

    def append(self, report: FrameEstimate) -> None:
        """Add the next frame's report; every ``block_frames`` reports go to disk as one block."""
        self._pending.append(report)
        self.last = report
        if len(self._pending) == self.block_frames:
            if self._folder is None:
                self._folder = temporary_folder()
            for name in FIELDS:
                save(self._path(self._written, name), self._stack_pending(name))
            self._written += 1
            self._pending = []

    def stack(self, name: str) -> np.ndarray:
        """(P, F, ...) the field ``name`` of every report, frame after frame (F = ``len(self)``)."""
        if not len(self):
            raise ValueError("no frame was reported")
        sample = getattr(self.last, name)
        out = np.empty((sample.shape[0], len(self)) + sample.shape[1:], sample.dtype)
        for block in range(self._written):
            out[:, block * self.block_frames : (block + 1) * self.block_frames] = np.load(self._path(block, name))
        if self._pending:
            out[:, self._written * self.block_frames :] = self._stack_pending(name)
        return out

    def close(self) -> None:
        """Remove the blocks written to disk (the reports are gone after this)."""
        if self._folder is not None:
            self._folder.cleanup()
            self._folder = None
        self._written, self._pending, self.last = 0, [], None

    def _stack_pending(self, name: str) -> np.ndarray:
        return np.stack([getattr(report, name) for report in self._pending], axis=1)

    def _path(self, block: int, name: str) -> Path:
        return Path(self._folder.name) / f"{block:06d}.{name}.npy"
