"""Contract of a ``detect`` stage: the first frame in, the points to track out.

A detector is registered with ``register("detect", name, SettingsModel)`` on the
function itself (a built-in one is a row of ``registry.BUILTINS`` instead), called
``detector(settings, gray) -> xy``:

- gray: (H, W) float32 grey levels in [0, 255] (``Frame.gray`` of the first frame);
- xy: (M, 2) float64 positions in px, x right, y down, (0, 0) the centre of the
  top-left pixel (``condtrack_cli/types.py``), best first; M may be 0.

The pipeline makes them queries on frame 0 with point ids 0..M-1 (``queries.detected_queries``), refusing any
other shape or dtype, a non-finite position or one outside the frame.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from condtrack_cli.settings import StageSettings


class Detector(Protocol):
    """``detector(settings, gray)``: (M, 2) float64 positions (px) of the points to track on a (H, W) float32 frame."""

    def __call__(self, settings: StageSettings, gray: np.ndarray) -> np.ndarray: ...
