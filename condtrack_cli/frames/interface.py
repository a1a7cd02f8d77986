"""Contract of a ``frames`` stage: an input path in, a stream of 8-bit grey frames out.

A frames stage is registered with ``register("frames", name, SettingsModel)`` on a
factory called ``factory(settings, path) -> FrameSource``; it raises
:class:`condtrack_cli.errors.CondtrackError` naming the path when the input cannot
be read. Frames are in the package's pixel convention (``condtrack_cli/types.py``).
The pipeline iterates a source (``iter``) once, on a reader thread, one frame ahead
of the tracking (``prefetch.py``); its errors reach the caller unchanged (a
plugin's own exceptions as a CondtrackError naming the stage: ``registry.StageSpec.call``). The
backward pass reads the frames the forward pass kept (``frame_reports.FrameStore``).
The built-in stages are rows of ``registry.BUILTINS`` instead.
"""

from __future__ import annotations

from typing import Iterator, Protocol

import numpy as np

from condtrack_cli.types import SequenceInfo


class FrameSource(Protocol):
    """An opened input: its size and frame count, and its frames."""

    info: SequenceInfo  #: width and height (px), n_frames, fps (0.0 when the input has no timing)

    def __iter__(self) -> Iterator[np.ndarray]:
        """Frames 0, 1, ..., n_frames - 1, each (H, W) uint8 grey (H = info.height, W = info.width)."""

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as (H, W) uint8."""
