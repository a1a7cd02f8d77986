"""Affine maps as (..., 2, 3) arrays [A | t] acting on points (..., 2) as A x + t (pixels)."""

from __future__ import annotations

import numpy as np


# An affine map is a (..., 2, 3) array [A | t] acting on x (..., 2) as A x + t.


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """m (..., 2, 3) applied to points x (..., 2) -> (..., 2), broadcasting."""
    return np.einsum("...ij,...j->...i", m[..., :2], x) + m[..., 2]


def _invert(m: np.ndarray) -> np.ndarray:
    """Inverse of affine maps (..., 2, 3)."""
    a_inv = np.linalg.inv(m[..., :2])
    return np.concatenate([a_inv, -np.einsum("...ij,...j->...i", a_inv, m[..., 2])[..., None]], axis=-1)


def _compose(outer: np.ndarray, inner: np.ndarray) -> np.ndarray:
    """Map ``outer o inner`` (first inner, then outer), both (..., 2, 3)."""
    a = outer[..., :2] @ inner[..., :2]
    t = np.einsum("...ij,...j->...i", outer[..., :2], inner[..., 2]) + outer[..., 2]
    return np.concatenate([a, t[..., None]], axis=-1)


def _about(centre: np.ndarray, linear: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """(2, 3) map x -> linear (x - centre) + centre + shift."""
    return np.concatenate([linear, (centre - linear @ centre + shift)[:, None]], axis=1)


def _rotation(angle: float, scale: float = 1.0) -> np.ndarray:
    """(2, 2) rotation by ``angle`` radians (clockwise on screen, y being down) times ``scale``."""
    c, s = np.cos(angle), np.sin(angle)
    return scale * np.array([[c, -s], [s, c]])


def _chain(increments: list[np.ndarray]) -> np.ndarray:
    """Frame 0 -> frame k maps (F, 2, 3) from the F-1 frame k-1 -> frame k maps."""
    maps = [np.eye(2, 3)]
    for step in increments:
        maps.append(_compose(step, maps[-1]))
    return np.stack(maps)


