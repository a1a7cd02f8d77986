"""Two-way smoothing (filter.smooth): the batched smoothers against plain per-point references, and end to end."""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import condtrack_cli as ct
from condtrack_cli.cli import cli
from condtrack_cli.config import load_config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.filters import kalman
from condtrack_cli.filters.smoother import particle_smoother, rts
from conftest import SAMPLES

P, F = 6, 14


def random_spd(rng: np.random.Generator, shape: tuple[int, ...], scale: float) -> np.ndarray:
    m = rng.normal(size=shape + (2, 2))
    return scale * (m @ np.swapaxes(m, -1, -2) + 0.5 * np.eye(2))


def linear_gaussian_filter(seed: int = 0):
    """A forward Kalman pass over P points with per-point, per-frame A_k, b_k, Q_k, R_k (eq. 1).

    Points start at different frames, some frames have no usable measurement
    (the point coasts), and one point changes segment (a handover) at frame 8.
    Returns the filtered xy, cov, the recorded x_pred, cov_pred, A and ``linked``.
    """
    rng = np.random.default_rng(seed)
    start = np.array([0, 0, 2, 5, 1, 0])
    A = np.eye(2) + 0.1 * rng.normal(size=(P, F, 2, 2))
    b = rng.normal(size=(P, F, 2))
    Q = random_spd(rng, (P, F), 0.3)
    R = random_spd(rng, (P, F), 1.0)
    valid = rng.random((P, F)) > 0.3
    truth = np.zeros((P, 2))
    xy, cov = np.full((P, F, 2), np.nan), np.full((P, F, 2, 2), np.nan)
    x_pred, cov_pred = np.full((P, F, 2), np.nan), np.full((P, F, 2, 2), np.nan)
    x, sigma = np.zeros((P, 2)), np.repeat(0.25 * np.eye(2)[None], P, 0)
    for k in range(F):
        on = np.flatnonzero(start < k)
        truth = np.einsum("pij,pj->pi", A[:, k], truth) + b[:, k] + rng.normal(size=(P, 2))
        z = truth + rng.normal(size=(P, 2))
        xp, sp = kalman.predict(x[on], sigma[on], A[on, k], b[on, k], Q[on, k])
        x_pred[on, k], cov_pred[on, k] = xp, sp
        x[on], sigma[on] = kalman.update(xp, sp, z[on], R[on, k], valid[on, k])
        here = start <= k
        xy[here, k], cov[here, k] = x[here], sigma[here]
    linked = np.isfinite(x_pred).all(axis=-1)
    linked[4, 8] = False  # point 4: a new segment starts at frame 8
    return xy, cov, x_pred, cov_pred, A, linked


def reference_rts(xy, cov, x_pred, cov_pred, A, linked):
    """Textbook RTS, one point and one frame at a time."""
    xs, cs = xy.copy(), cov.copy()
    for p in range(xy.shape[0]):
        for k in range(xy.shape[1] - 2, -1, -1):
            if not linked[p, k + 1]:
                continue
            gain = cov[p, k] @ A[p, k + 1].T @ np.linalg.inv(cov_pred[p, k + 1])
            xs[p, k] = xy[p, k] + gain @ (xs[p, k + 1] - x_pred[p, k + 1])
            cs[p, k] = cov[p, k] + gain @ (cs[p, k + 1] - cov_pred[p, k + 1]) @ gain.T
    return xs, cs


def test_rts_equals_a_per_point_reference_on_a_linear_gaussian_case():
    arrays = linear_gaussian_filter()
    xs, cs = rts(*arrays)
    ref_x, ref_c = reference_rts(*arrays)
    np.testing.assert_allclose(xs, ref_x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cs, ref_c, rtol=0, atol=1e-9)
    xy, cov, *_, linked = arrays
    assert np.array_equal(np.isnan(xs), np.isnan(xy))  # no state before a point's start
    assert np.abs(xs[:, -1] - xy[:, -1]).max() == 0  # the last frame is the filter's
    assert np.abs(xs[4, 7] - xy[4, 7]).max() == 0  # so is the last frame before a new segment
    assert np.abs(xs[4, 6] - xy[4, 6]).max() > 1e-3  # and the frames before it are smoothed
    # smoothing never loses information: Sigma_{k|F} <= Sigma_{k|k}
    finite = np.isfinite(cs).all(axis=(-1, -2))
    assert (np.linalg.eigvalsh(cov[finite] - cs[finite]) > -1e-9).all()


def reference_ffbsm(particles, log_w, mu, Q, linked):
    """FFBSm weights, one point, frame and particle pair at a time; then the weighted moments."""
    p_count, f_count, n, _ = particles.shape
    w = np.exp(log_w)
    ws = w.copy()

    def density(x, m, c):
        d = x - m
        return np.exp(-0.5 * d @ np.linalg.inv(c) @ d) / (2 * np.pi * np.sqrt(np.linalg.det(c)))

    for p in range(p_count):
        for k in range(f_count - 2, -1, -1):
            if not linked[p, k + 1]:
                continue
            f = np.array([[density(particles[p, k + 1, j], mu[p, k + 1, i], Q[p, k + 1, i]) for j in range(n)]
                          for i in range(n)])
            for i in range(n):
                ws[p, k, i] = w[p, k, i] * sum(ws[p, k + 1, j] * f[i, j] / (w[p, k] @ f[:, j]) for j in range(n))
            ws[p, k] /= ws[p, k].sum()
    mean = np.einsum("pfn,pfni->pfi", ws, particles)
    d = particles - mean[:, :, None]
    return mean, np.einsum("pfn,pfni,pfnj->pfij", ws, d, d)


def test_particle_smoother_equals_a_per_point_reference():
    rng = np.random.default_rng(1)
    n = 7
    particles = rng.normal(scale=2.0, size=(3, 5, n, 2))
    log_w = np.log(rng.dirichlet(np.ones(n), size=(3, 5)))
    mu = particles + rng.normal(scale=0.5, size=particles.shape)  # only frames k >= 1 are read
    Q = random_spd(rng, (3, 5, n), 1.0)
    linked = np.ones((3, 5), bool)
    linked[:, 0] = False
    linked[2, 3] = False
    mean, cov = particle_smoother(particles, log_w, mu, Q, linked)
    ref_mean, ref_cov = reference_ffbsm(particles, log_w, mu, Q, linked)
    np.testing.assert_allclose(mean, ref_mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cov, ref_cov, rtol=0, atol=1e-9)


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
@pytest.mark.parametrize("method", ["cnlf", "auto"])
def test_smoothed_tracks_are_deterministic_and_differ_from_the_filtered(shifted_folder, method):
    folder, shifts = shifted_folder
    queries = np.array([[0, 120.0, 100.0], [2, 200.0 + shifts[2, 0], 150.0 + shifts[2, 1]]])  # one queried mid-clip
    config = {"filter": {"smooth": True, "cnlf": {"particles": 30}}}
    first = ct.track(folder, queries=queries, method=method, config=config, seed=4)
    second = ct.track(folder, queries=queries, method=method, config=config, seed=4)
    assert np.array_equal(first.xy, second.xy, equal_nan=True) and np.array_equal(first.cov, second.cov, equal_nan=True)
    assert np.isfinite(first.xy).all() and np.isfinite(first.cov).all()
    filtered = ct.track(folder, queries=queries, method=method, config={"filter": {"smooth": False, "cnlf": {"particles": 30}}}, seed=4)
    assert not np.array_equal(first.cov, filtered.cov)


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_smoothing_narrows_the_filters_covariance_and_keeps_the_error_models_excess(shifted_folder):
    """RTS narrows Sigma only; what the error model added (filters/calibration.py) stays, frame by frame.

    The last frame has no later frame: its smoothed covariance is the reported
    one, error model included; on the others it is no wider than the reported one.
    """
    folder, _ = shifted_folder
    queries = np.array([[0, 120.0, 100.0], [0, 200.0, 150.0], [0, 160.0, 60.0]])
    filtered = ct.track(folder, queries=queries, method="clf")
    smoothed = ct.track(folder, queries=queries, method="clf", config={"filter": {"smooth": True}})
    assert np.array_equal(smoothed.cov[:, -1], filtered.cov[:, -1])
    trace = lambda c: np.trace(c, axis1=-2, axis2=-1)  # noqa: E731
    assert (trace(smoothed.cov) <= trace(filtered.cov) + 1e-12).all()
    assert (trace(smoothed.cov[:, 1:-1]) < trace(filtered.cov[:, 1:-1])).any()


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")
@pytest.mark.parametrize("method", ["clf", "cnlf", "auto"])
def test_smoothing_keeps_each_query_row_and_positive_covariances(method):
    """Smoothed or not, a query row is the query with the forward pass's covariance, and every covariance is positive
    semi-definite. The occlusion sample's flat top-left corner fails the trackability test, so those queries start
    with a wide aperture offset: the CLF's RTS, which reads the filter's own spread there, put negative variances on
    their query rows and moved them off the query; the CNLF's FFBSm dropped the offset. One query is mid-clip (a
    backward pass)."""
    queries = np.array([[0, 10.0, 10.0], [0, 160.0, 120.0], [12, 10.0, 10.0]])
    config = {"filter": {"cnlf": {"particles": 30}}}
    filtered = ct.track(SAMPLES / "occlusion", queries=queries, method=method, config=config)
    smoothed = ct.track(SAMPLES / "occlusion", queries=queries, method=method,
                        config={"filter": {**config["filter"], "smooth": True}})
    rows = (np.arange(len(queries)), queries[:, 0].astype(int))
    np.testing.assert_array_equal(smoothed.xy[rows], queries[:, 1:])
    np.testing.assert_array_equal(smoothed.cov[rows], filtered.cov[rows])
    assert np.trace(filtered.cov[rows][[0, 2]], axis1=1, axis2=2).min() > 1.0  # the aperture offset, not 2 x 0.5^2
    finite = np.isfinite(smoothed.cov).all(axis=(-2, -1))
    assert finite[rows].all() and (np.linalg.eigvalsh(smoothed.cov[finite]) >= 0).all()


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_smooth_flag_is_recorded_in_the_hdf5_and_refused_for_a_method_without_smoother(shifted_folder, tmp_path):
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,120,100\n")
    out = tmp_path / "t.h5"
    result = CliRunner().invoke(cli, ["track", str(folder), "-p", str(queries), "-m", "clf", "--smooth", "-o", str(out), "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(out) as f:
        assert f.attrs["smoothed"] == True  # noqa: E712 (numpy bool)
    refused = tmp_path / "refused.h5"
    result = subprocess.run(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(folder), "-p", str(queries),
         "-m", "stk", "--smooth", "-o", str(refused), "-q"], capture_output=True, text=True, timeout=300,
    )
    assert result.returncode != 0 and not refused.exists()
    assert result.stderr == "Error: config key 'filter.smooth': method 'stk' has no smoother\n"


def test_filter_smooth_must_be_a_boolean():
    with pytest.raises(CondtrackError, match="filter.smooth"):
        load_config({"filter": {"smooth": "yes"}})


@pytest.mark.parametrize("method", ["stk", "mdr"])
def test_smooth_without_a_smoother_is_refused_before_any_input_is_read_or_output_made(tmp_path, method):
    """--smooth with a method that has no smoother was refused only once the first frame was tracked: a batch made
    OUT_DIR and failed each input in turn, and an unreadable input was reported instead of the option. It is now
    refused when the config is read, by the command line, a batch and ct.track alike."""
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "0.png").write_bytes(b"not a png")
    said = f"config key 'filter.smooth': method '{method}' has no smoother"
    out_dir = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(broken), str(SAMPLES / "ring"),
         "-m", method, "--smooth", "--out-dir", str(out_dir), "-q"], capture_output=True, text=True, timeout=300,
    )
    assert (result.returncode, result.stderr) == (1, f"Error: {said}\n") and not out_dir.exists()
    with pytest.raises(CondtrackError, match=f"^{said}$"):
        ct.track(broken, config={"filter": {"method": method, "smooth": True}})
