"""The per-frame pipeline: frames -> (detection) -> filter -> tracks.

The filter composes the motion and measurement stages it needs; the pipeline
streams frames, keeps only the previous and the current one, and hands each
frame's report to an optional ``on_frame`` callback (progress display).
"""

from __future__ import annotations

from typing import Callable, Iterable

import numpy as np

from condtrack_cli import registry
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.queries import detected_queries
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks


def detect_queries(config: Config, first: Frame) -> Queries:
    """Queries detected on the first frame with the configured detector."""
    stage = config.stage("detect")
    xy = registry.get("detect", stage.name).factory(stage.settings, first.gray)
    return detected_queries(xy)


def run(
    frames: Iterable[np.ndarray],
    info: SequenceInfo,
    config: Config,
    queries: Queries | None = None,
    seed: int = 0,
    on_frame: Callable[[int, FrameEstimate], None] | None = None,
) -> Tracks:
    """Track ``queries`` (detected on frame 0 when None) through ``frames`` with ``config.method``."""
    spec = registry.get("filter", config.method)
    tracker = None
    history: list[FrameEstimate] = []
    prev: Frame | None = None
    for index, image in enumerate(frames):
        frame = Frame(index, image)
        if tracker is None:
            if queries is None:
                queries = detect_queries(config, frame)
                if not len(queries):
                    raise CondtrackError(f"{info.input}: no trackable point detected on frame 0")
            tracker = spec.factory(
                config.filters[config.method], queries=queries, info=info, config=config,
                rng=np.random.default_rng(seed),
            )
        history.append(tracker.step(frame, prev))
        if on_frame is not None:
            on_frame(index, history[-1])
        prev = frame
    if tracker is None:
        raise CondtrackError(f"{info.input}: the input has no frame")
    return tracker.finish(history)
