"""The per-frame pipeline: frames -> (detection) -> motion -> filter -> tracks; the stages built from the Config.

This module is where the Config becomes stages (``api.py`` opens the frames):
``build_tracker`` builds the configured measurement stage and hands the filter's
factory it, the motion stage's Q_k and plain values (``filters/interface.py``);
no stage reads the config or another stage's settings. Per frame pair k-1 -> k
the pipeline estimates the motion the filter asks for (the global fit, and the
local field only when ``tracker.needs_local_motion``) and passes it to
``tracker.step(frame, prev, motion)``. It streams frames, keeps only the
previous and the current one (each carries its pyramid, built once), keeps the
frames' reports on disk in blocks (``frame_reports.py``: memory flat in the
clip's length) and hands each to an optional ``on_frame`` callback (progress
display); the motion stage's work arrays go before the pass's reports are stacked.
A reader thread decodes the next frame while the current one is tracked
(``frames/prefetch.py``), and with more than one OpenCV thread (``--threads``) a
second thread estimates the motion of the pair k -> k+1 while the filter steps
frame k (``_track_frames``), and a third computes the dense field of the pair after
it (``frame_motions``): the work of all, mostly in OpenCV and numpy, which
release the GIL, runs on two cores; the tracks are those of one thread bit for bit.

A point queried at frame k > 0 is tracked forward from k and backward from k:
the backward pass runs the same filter on the time-reversed frames k_max .. 0
(k_max the latest query frame), so every point has a position on every frame.

With ``filter.smooth`` each pass is smoothed on its own, in its own time
direction, before the two are merged: the forward pass over frames q..F-1 of
each point, the backward pass over q..0. Both start from the query itself
(std ``initial_std``), which ties them at frame q, so little is lost by not
fusing them across it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Iterator

import contextlib
import dataclasses
import math

import numpy as np

from condtrack_cli import registry
from condtrack_cli.config import Config
from condtrack_cli.detect.trackability import Aperture, QueryScorer, trackability_settings
from condtrack_cli.errors import CondtrackError, counted
from condtrack_cli.filters.gauss2 import symmetrize
from condtrack_cli.filters.interface import Tracker
from condtrack_cli.frame_reports import FrameReports, FrameStore, park, temporary_folder
from condtrack_cli.frames.prefetch import Prefetched
from condtrack_cli.motion.interface import FrameMotion, MotionStages, PairFieldSource
from condtrack_cli.queries import detected_queries
from condtrack_cli.threads import threads_in_use
from condtrack_cli.types import Frame, FrameEstimate, Queries, SequenceInfo, Tracks

#: The name of the thread that estimates the motion one frame pair ahead of the filter.
MOTION_THREAD = "condtrack-motion-ahead"

#: The name of the thread that computes a motion stage's field one frame pair ahead of its estimators.
FIELD_THREAD = "condtrack-field-ahead"


def build_stage(config: Config, kind: str):
    """The configured stage of ``kind`` ('motion', 'measure'), built from its settings alone (a plugin's guarded and
    its measurer's outputs checked: ``registry.StageSpec.build``)."""
    stage = config.stage(kind)
    return registry.get(kind, stage.name).build(stage.settings)


def detect_queries(config: Config, first: Frame, info: SequenceInfo) -> Queries:
    """Queries detected on the first frame with the configured detector (its output checked: ``queries.py``)."""
    stage = config.stage("detect")
    xy = registry.get("detect", stage.name).build(stage.settings, first.gray)
    return detected_queries(xy, info, stage.name)


def build_tracker(config: Config, queries: Queries, info: SequenceInfo, rng: np.random.Generator,
                  motion: MotionStages) -> Tracker:
    """The configured filter (``config.method``), its factory handed every keyword of ``filters/interface.py``."""
    return registry.get("filter", config.method).build(
        config.filters[config.method], queries=queries, info=info, rng=rng,
        measure=build_stage(config, "measure"), gamma=config.stage("measure").settings.gamma,
        state_noise=motion.state_noise, smooth=config.smooth, store_particles=config.output.store_particles,
        store_segmentation=config.output.store_segmentation, filter_settings=config.filters,
        aperture=Aperture(*trackability_settings(config.stage("detect").settings)[:2]),
    )


def frame_motion(motion: MotionStages, prev: Frame, frame: Frame, local: bool) -> FrameMotion:
    """The motion from ``prev`` to ``frame``: the global fit, and the local field on it when ``local``."""
    fit = motion.global_motion.fit(prev, frame)
    return FrameMotion(fit, motion.local_motion.field(prev, frame, fit) if local else None)


def run(
    source,
    info: SequenceInfo,
    config: Config,
    queries: Queries | None = None,
    seed: int = 0,
    on_frame: Callable[[int, FrameEstimate], None] | None = None,
) -> Tracks:
    """Track ``queries`` (detected on frame 0 when None) through ``source`` in both directions.

    ``source`` iterates (H, W) uint8 frames (the frame readers). The backward pass
    uses the seed ``seed + 1`` and reads the forward pass's frames from a
    ``FrameStore`` (frames 0..k_max on disk); with ``output.backward`` false there is
    none, and a point has no state before its query frame.
    """
    last = backward_start(config, queries)
    if last == 0:
        return _whole(run_pass(source, info, config, queries, seed, on_frame), info)
    with temporary_folder() as folder:
        store = FrameStore(Path(folder) / "frames.u8", last)
        forward = _whole(run_pass(store.keeping(source), info, config, queries, seed, on_frame), info)
        forward = park(forward, Path(folder))  # waits on disk while the backward pass runs (memory flat in length)
        mirrored = Queries(queries.point_id, last - queries.frame, queries.xy)
        backward = run_pass(store.reversed(), info, config, mirrored, seed + 1, on_frame)
        merged = merge_backward(forward, backward)
        del forward  # the memory maps go before their files
    return merged


def _whole(forward: Tracks, info: SequenceInfo) -> Tracks:
    """The forward pass's ``forward`` tracks; CondtrackError where the input gave fewer frames than ``info.n_frames``,
    counted when it was opened (a video whose decoding stops earlier on the second reading: a damaged file, or one
    that changed while it was read)."""
    read = forward.xy.shape[1]
    if read != info.n_frames:
        raise CondtrackError(f"{info.input}: {counted(info.n_frames, 'frame')} when it was opened, but reading stopped "
                             f"after {read} (a damaged file, or one that changed while it was read?)")
    return forward


def backward_start(config: Config, queries: Queries | None) -> int:
    """The frame the backward pass starts from, k_max (the latest query frame); 0: there is no backward pass
    (no query after frame 0, detected queries, or ``output.backward`` false)."""
    return int(queries.frame.max()) if queries is not None and len(queries) and config.output.backward else 0


def merge_backward(forward: Tracks, backward: Tracks) -> Tracks:
    """Tracks with ``backward``'s (time-reversed, frames last..0) rows before each query frame.

    The optional datasets (``extras``: particles, segmentation) and the trackability scores are the forward pass's.
    """
    last = backward.xy.shape[1] - 1
    before = np.arange(forward.xy.shape[1])[None, :] < forward.queries.frame[:, None]  # (P, F)

    def combine(ahead: np.ndarray, behind: np.ndarray) -> np.ndarray:
        ahead = np.asarray(ahead)  # a parked (memory-mapped) array as a plain one: the result is in memory
        padded = np.full_like(ahead, np.nan if ahead.dtype.kind == "f" else 0)
        padded[:, : last + 1] = behind[:, ::-1]
        mask = before.reshape(before.shape + (1,) * (ahead.ndim - 2))
        return np.where(mask, padded, ahead)

    return Tracks(
        queries=forward.queries, xy=combine(forward.xy, backward.xy), cov=combine(forward.cov, backward.cov),
        dof=combine(forward.dof, backward.dof), visible=combine(forward.visible, backward.visible),
        method=combine(forward.method, backward.method), z=combine(forward.z, backward.z),
        R=combine(forward.R, backward.R), extras=forward.extras, trackability=forward.trackability,
    )


def run_pass(
    frames: Iterable[np.ndarray],
    info: SequenceInfo,
    config: Config,
    queries: Queries | None,
    seed: int,
    on_frame: Callable[[int, FrameEstimate], None] | None,
) -> Tracks:
    """One pass of ``config.method`` through ``frames`` (frame i of the iterable is frame i of the pass).

    The motion of a frame pair is estimated when the tracker needs it and a point
    was started before the pair's second frame.
    """
    with FrameReports() as history:
        with Prefetched(frames) as ahead:  # frame k+1 is decoded while frame k is tracked
            tracker, scores = _track_frames(ahead, info, config, queries, seed, on_frame, history)
        tracks = dataclasses.replace(tracker.finish(history), trackability=scores)
    tracks = query_rows_kept(tracks, tracker.smooth(tracks)) if config.smooth else tracks
    return dataclasses.replace(
        tracks, cov=symmetrize(np.require(tracks.cov, np.float64, "W")),  # copied if read-only
        visible=tracks.visible & info.contains(tracks.xy),  # a point that left the frame is not seen, wherever it is
    )


def query_rows_kept(filtered: Tracks, smoothed: Tracks) -> Tracks:
    """``smoothed`` with each point's query row as the forward pass ``filtered`` reports it: the query and its
    covariance (the initial one, with a query's aperture offset where it fails the trackability test).

    Smoothed or not, the query row is the user's query (docs/departures.md, "CNLF path estimate"). The smoothers
    would move it by the later frames' evidence, and they read the filters' spread there, the filters' device
    (``initial_std``), not what the error model reports: the CLF's RTS put negative variances on the query rows of
    untrackable queries, and the CNLF's FFBSm dropped their aperture offset.
    """
    started = np.flatnonzero(filtered.queries.frame < filtered.xy.shape[1])  # a clip may end before a query
    rows = (started, filtered.queries.frame[started])
    xy, cov = smoothed.xy.copy(), smoothed.cov.copy()
    xy[rows], cov[rows] = filtered.xy[rows], filtered.cov[rows]
    return dataclasses.replace(smoothed, xy=xy, cov=cov)


def frame_motions(images: Iterable[np.ndarray], prev: Frame, motion: MotionStages, local: bool,
                  moving_from: float, fields_ahead: bool = False) -> Iterator[tuple[Frame, FrameMotion | None]]:
    """Each frame after ``prev`` (``images`` are frames ``prev.index + 1``, ...) with the motion of the pair ending
    there (``frame_motion``; ``local``: with the local field), estimated from frame index ``moving_from`` on.

    ``fields_ahead``: the stage's ``field_source`` (when it has one) computes each pair's field in a thread of its
    own (``FIELD_THREAD``), a pair ahead of the estimators, which are given it (``prime``): where the filter's own
    step is the cheaper part (``clf`` on a KITTI clip), the field and the rest of the motion overlap. The same
    fields, the same motion, bit for bit. Only the last two frames are kept (their pyramids)."""
    source = motion.field_source if fields_ahead else None
    with (Prefetched(_pair_fields(images, prev, source, moving_from), name=FIELD_THREAD) if source is not None
          else contextlib.nullcontext((image, None) for image in images)) as pairs:
        for index, (image, field) in enumerate(pairs, prev.index + 1):
            frame = Frame(index, image)
            if field is not None:
                source.prime(prev, frame, field)
            yield frame, frame_motion(motion, prev, frame, local) if index >= moving_from else None
            prev = frame


def _pair_fields(images: Iterable[np.ndarray], prev: Frame, source: PairFieldSource,
                 moving_from: float) -> Iterator[tuple[np.ndarray, np.ndarray | None]]:
    """Each image after ``prev`` (as in :func:`frame_motions`) with the field of the pair ending there (None before
    frame index ``moving_from``)."""
    before = prev.image
    for index, image in enumerate(images, prev.index + 1):
        yield image, source.compute(before, image) if index >= moving_from else None
        before = image


def _track_frames(frames: Iterable[np.ndarray], info: SequenceInfo, config: Config, queries: Queries | None,
                  seed: int, on_frame: Callable[[int, FrameEstimate], None] | None,
                  history: FrameReports) -> tuple[Tracker, np.ndarray]:
    """Step the tracker through ``frames``, each frame's report appended to ``history``; the tracker and the
    (P,) trackability scores of the queries (``detect/trackability.py``), each taken on its query frame.

    The motion of a pair is estimated when the tracker needs it and a point was started before the pair's
    second frame. When OpenCV may use more than one thread, a thread estimates it one pair ahead
    (``frame_motions`` in a ``Prefetched``): the pair k -> k+1 while the tracker steps frame k. That thread
    has Frames of its own (their pyramids, their grey images), so no lazy attribute of a Frame is ever
    computed by both threads; the motion stage is used by that thread alone. The motion stage and the frames
    (work arrays, pyramids) are let go when this returns, before the tracker stacks the pass.
    """
    motion = build_stage(config, "motion")
    frames = iter(frames)
    image = next(frames, None)
    if image is None:
        raise CondtrackError(f"{info.input}: the input has no frame")
    first = Frame(0, image)
    if queries is None:
        queries = detect_queries(config, first, info)
        if not len(queries):
            raise CondtrackError(f"{info.input}: no trackable point detected on frame 0")
    tracker = build_tracker(config, queries, info, np.random.default_rng(seed), motion)
    scorer = QueryScorer(queries, trackability_settings(config.stage("detect").settings)[0])
    # the pair k-1 -> k moves when a point was started before k
    moving_from = int(queries.frame.min()) + 1 if tracker.needs_motion and len(queries) else math.inf
    ahead = moving_from < math.inf and threads_in_use()["opencv"] > 1
    pairs = frame_motions(frames, Frame(0, image) if ahead else first, motion, tracker.needs_local_motion, moving_from,
                          fields_ahead=ahead)

    def step(frame: Frame, prev: Frame | None, pair_motion: FrameMotion | None) -> None:
        scorer.see(frame.index, frame.gray)
        history.append(tracker.step(frame, prev, pair_motion))
        if on_frame is not None:
            on_frame(frame.index, history.last)

    with Prefetched(pairs, name=MOTION_THREAD) if ahead else contextlib.nullcontext(pairs) as pairs:
        step(first, None, None)
        prev = first
        del first  # from here on frame 0 is kept no longer than any frame (its grey image, its pyramid)
        for frame, pair_motion in pairs:
            if ahead:  # the motion thread goes on with its own Frame: no Frame is shared between the threads
                frame = Frame(frame.index, frame.image)
            step(frame, prev, pair_motion)
            prev = frame
    return tracker, scorer.scores
