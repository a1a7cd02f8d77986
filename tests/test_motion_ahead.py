"""The motion stage one frame pair ahead of the filter, in a thread (``pipeline._track_frames``, issue 26 item 6).

With more than one OpenCV thread the pipeline estimates the motion of the pair
k -> k+1 in a thread while the filter steps frame k, and the DIS field of the
pair after it in another (``pipeline.frame_motions``): the tracks must be those
of the plain loop (one thread) bit for bit, the threads at most one pair ahead,
their errors raised in the caller as the same exception, and no thread left
behind however the run ends.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading

import cv2
import numpy as np
import pytest

from condtrack_cli import pipeline
from condtrack_cli.config import load_config
from condtrack_cli.types import Queries

from conftest import sample_inputs


@contextlib.contextmanager
def opencv_threads(count: int):
    """OpenCV's pool sized ``count`` (what ``--threads`` sets) inside the block."""
    before = cv2.getNumThreads()
    cv2.setNumThreads(count)
    try:
        yield
    finally:
        cv2.setNumThreads(before)


def _motion_threads(name: str = pipeline.MOTION_THREAD) -> list[threading.Thread]:
    return [thread for thread in threading.enumerate() if thread.name == name]


@pytest.fixture(scope="module")
def clip():
    """(frame source, queries): the camera_motion sample, a third of the points queried at frames 12 and 29 (a
    backward pass; pairs before frame 1 of a pass without motion)."""
    source, _, truth = sample_inputs("camera_motion")
    seen = np.flatnonzero(truth.visible[:, [0, 12, 29]].all(axis=1))
    k = np.array([0, 12, 29])[np.arange(len(seen)) % 3]
    return source, Queries(truth.point_id[seen], k, truth.gt_xy[seen, k])


@pytest.mark.parametrize("method, smooth", [("clf", False), ("clf", True), ("cnlf", False), ("auto", False)])
def test_the_threaded_motion_gives_the_plain_loops_tracks_bit_for_bit(clip, method, smooth):
    source, queries = clip
    config = load_config(None, [f"filter.smooth={str(smooth).lower()}"], method)
    runs = {}
    for threads in (1, 2):
        ahead, fields = [], []

        def seen(index, _):
            ahead.append(bool(_motion_threads()))
            fields.append(bool(_motion_threads(pipeline.FIELD_THREAD)))

        with opencv_threads(threads):
            runs[threads] = pipeline.run(source, source.info, config, queries, on_frame=seen)
        assert any(ahead) == (threads > 1)  # the motion thread ran beside the filter with 2 threads, never with 1
        assert any(fields) == (threads > 1)  # and the field thread beside it
    for field in dataclasses.fields(runs[1]):
        if field.name not in ("queries", "extras"):
            plain, threaded = getattr(runs[1], field.name), getattr(runs[2], field.name)
            assert np.array_equal(plain, threaded, equal_nan=plain.dtype.kind == "f"), field.name
    assert not _motion_threads() and not _motion_threads(pipeline.FIELD_THREAD)


def test_the_motion_thread_is_at_most_one_pair_ahead(clip, monkeypatch):
    """At most one pair's motion arrays beyond the filter's (memory)."""
    source, queries = clip
    estimated, lead = [], []
    frame_motion = pipeline.frame_motion

    def counted(motion, prev, frame, local):
        estimated.append(frame.index)
        return frame_motion(motion, prev, frame, local)

    monkeypatch.setattr(pipeline, "frame_motion", counted)
    with opencv_threads(2):
        pipeline.run_pass(source, source.info, load_config(None, [], "clf"), queries, 0,
                          lambda index, _: lead.append(max(estimated, default=index) - index))
    assert estimated == list(range(1, source.info.n_frames)) and max(lead) <= 1


@pytest.mark.parametrize("threads", [1, 2])
def test_an_error_in_the_motion_stage_reaches_the_caller_unchanged(clip, monkeypatch, threads):
    source, queries = clip
    failure = ValueError("motion failed")
    frame_motion = pipeline.frame_motion

    def failing(motion, prev, frame, local):
        if frame.index == 5:
            raise failure
        return frame_motion(motion, prev, frame, local)

    monkeypatch.setattr(pipeline, "frame_motion", failing)
    stepped = []
    before = set(threading.enumerate())
    with opencv_threads(threads), pytest.raises(ValueError) as raised:
        pipeline.run(source, source.info, load_config(None, [], "clf"), queries,
                     on_frame=lambda index, _: stepped.append(index))
    assert raised.value is failure
    assert stepped == [0, 1, 2, 3, 4]  # the frames before the failing pair were tracked
    assert set(threading.enumerate()) == before


@pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError])
def test_a_run_ending_early_stops_and_joins_the_motion_thread(clip, error):
    """Ctrl-C (KeyboardInterrupt) or any error in the filter's thread while the motion thread runs."""
    source, queries = clip

    def stop(index, _):
        if index == 3:
            assert _motion_threads()
            raise error

    before = set(threading.enumerate())
    with opencv_threads(2), pytest.raises(error):
        pipeline.run(source, source.info, load_config(None, [], "cnlf"), queries, on_frame=stop)
    assert set(threading.enumerate()) == before


def test_an_error_in_the_field_thread_reaches_the_caller_unchanged(clip, monkeypatch):
    """The DIS field of a pair fails in the field thread: the frames before it were tracked, the same exception
    reaches the caller, and both threads are joined."""
    from condtrack_cli.motion.dense import DenseFlow

    source, queries = clip
    failure = ValueError("field failed")
    compute, calls = DenseFlow.compute, []

    def failing(self, prev, cur):
        calls.append(threading.current_thread().name)
        if len(calls) == 5:
            raise failure
        return compute(self, prev, cur)

    monkeypatch.setattr(DenseFlow, "compute", failing)
    stepped = []
    before = set(threading.enumerate())
    with opencv_threads(2), pytest.raises(ValueError) as raised:
        pipeline.run(source, source.info, load_config(None, [], "clf"), queries,
                     on_frame=lambda index, _: stepped.append(index))
    assert raised.value is failure
    assert stepped == [0, 1, 2, 3, 4] and set(calls) == {pipeline.FIELD_THREAD}
    assert set(threading.enumerate()) == before
