"""The vectorised Kalman algebra equals a plain per-point implementation of Fig. 1 to 1e-12."""

from __future__ import annotations

import numpy as np

from condtrack_cli.filters import kalman


def _spd(rng, n):
    m = rng.normal(size=(n, 2, 2))
    return m @ np.swapaxes(m, 1, 2) + 0.1 * np.eye(2)


def _reference(x, sigma, A, b, Q, z, R, valid):
    """One point at a time, in the paper's notation (Fig. 1)."""
    xs, ss = [], []
    for i in range(len(x)):
        x_pred = A[i] @ x[i] + b[i]
        s_pred = A[i] @ sigma[i] @ A[i].T + Q[i]
        if valid[i]:
            K = s_pred @ np.linalg.inv(s_pred + R[i])
            x_post = x_pred + K @ (z[i] - x_pred)
            s_post = (np.eye(2) - K) @ s_pred
        else:
            x_post, s_post = x_pred, s_pred
        xs.append(x_post)
        ss.append(s_post)
    return np.array(xs), np.array(ss)


def test_batched_filter_equals_per_point_reference():
    rng = np.random.default_rng(11)
    n = 64
    x, b, z = rng.normal(size=(n, 2)) * 50, rng.normal(size=(n, 2)), rng.normal(size=(n, 2)) * 50
    A = np.eye(2) + 0.05 * rng.normal(size=(n, 2, 2))
    sigma, Q, R = _spd(rng, n), _spd(rng, n), _spd(rng, n)
    valid = rng.random(n) < 0.7
    inputs = [a.copy() for a in (x, sigma, A, b, Q, z, R)]
    x_pred, s_pred = kalman.predict(x, sigma, A, b, Q)
    x_post, s_post = kalman.update(x_pred, s_pred, z, R, valid)
    x_ref, s_ref = _reference(x, sigma, A, b, Q, z, R, valid)
    np.testing.assert_allclose(x_post, x_ref, rtol=0, atol=1e-12 * np.abs(x_ref).max())
    np.testing.assert_allclose(s_post, s_ref, rtol=0, atol=1e-12 * np.abs(s_ref).max())
    for before, after in zip(inputs, (x, sigma, A, b, Q, z, R)):
        np.testing.assert_array_equal(before, after)  # inputs untouched


def test_mahalanobis():
    nu = np.array([[3.0, 0.0], [0.0, 2.0]])
    S = np.array([np.diag([9.0, 1.0]), np.diag([1.0, 4.0])])
    np.testing.assert_allclose(kalman.mahalanobis2(nu, S), [1.0, 1.0])
