"""CLF on the samples: occluded points coast unseen and are re-acquired; CLF beats STK; the
per-point choice of dynamics (``select``) keeps the occlusion sample and gains on the ring.

Measured: occlusion sample CLF <delta_avg 0.983, AJ 0.939 against STK 0.807, 0.598; 27
occlusion runs of >= 3 frames, points reported visible on 8% of the covered
frames, 24 of 27 back within 1 px one frame after they reappear (25 with the plain
SSD cost, docs/departures.md). Ring sample: select 0.908, global 0.824, local 0.870;
occlusion sample: select 0.983, global 0.985, local 0.810.
"""

from __future__ import annotations

import numpy as np
import pytest

from condtrack_cli import pipeline
from condtrack_cli.config import load_config
from condtrack_cli.evaluate.score import score_tracks

from conftest import sample_inputs


@pytest.fixture(scope="module")
def occlusion_runs():
    source, queries, truth = sample_inputs("occlusion")
    return {
        method: score_tracks(pipeline.run(source, source.info, load_config(None, method=method), queries), truth)
        for method in ("stk", "clf")
    }


def test_clf_beats_stk_on_the_occlusion_sample(occlusion_runs):
    clf, stk = occlusion_runs["clf"][0], occlusion_runs["stk"][0]
    assert clf["delta_avg"] > stk["delta_avg"] + 0.1
    assert clf["AJ"] > stk["AJ"] + 0.2


def _occlusion_runs(visible: np.ndarray, query_frame: np.ndarray, min_length: int = 3):
    """(point, first covered frame, first visible frame after) of every run of >= min_length covered frames."""
    runs = []
    for point, row in enumerate(visible):
        hidden = np.concatenate([[False], ~row[query_frame[point] + 1 :], [False]]).astype(int)
        starts = np.flatnonzero(np.diff(hidden) == 1) + query_frame[point] + 1
        ends = np.flatnonzero(np.diff(hidden) == -1) + query_frame[point] + 1
        runs += [(point, s, e) for s, e in zip(starts, ends) if e - s >= min_length and e < row.size]
    return runs


def test_occluded_points_are_not_visible_and_come_back(occlusion_runs):
    _, data = occlusion_runs["clf"]
    runs = _occlusion_runs(data.gt_visible, data.query_frame)
    assert len(runs) >= 10
    covered = np.concatenate([data.pred_visible[p, s:e] for p, s, e in runs])
    assert covered.mean() <= 0.10  # reported not visible on at least 90% of the covered frames
    error = np.linalg.norm(data.pred_xy - data.gt_xy, axis=-1)
    back = np.array([error[p, min(e + 1, error.shape[1] - 1)] for p, s, e in runs])
    assert (back < 1.0).mean() >= 0.85  # re-acquired within 1 px one frame after reappearing


@pytest.mark.parametrize(("sample", "global_at_least", "local_at_most"), [("ring", 0.05, None), ("occlusion", -0.01, -0.1)])
def test_selected_dynamics_keep_the_better_motion(sample, global_at_least, local_at_most):
    """select >= global + margin (ring: the disk's points need their local motion); on the occlusion
    sample select stays with global (within 0.01) while local alone loses (a covered point's window
    follows the occluder)."""
    source, queries, truth = sample_inputs(sample)

    def delta(dynamics: str) -> float:
        config = load_config(None, [f"filter.clf.dynamics={dynamics}"], method="clf")
        return score_tracks(pipeline.run(source, source.info, config, queries), truth)[0]["delta_avg"]

    select, global_ = delta("select"), delta("global")
    assert select >= global_ + global_at_least
    if local_at_most is not None:
        assert delta("local") <= global_ + local_at_most
