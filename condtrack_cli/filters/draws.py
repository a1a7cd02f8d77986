"""Random draws that belong to one point, one frame and one use (the CNLF's particles and resampling).

A particle filter run over many points from one random stream couples them: a
point that needs a draw more or fewer (a resampling that one rounding tipped, a
point that ``auto`` handed to the other filter) shifts the stream under every
point that draws after it, and all their particles change. With one stream the
same run on another CPU differed on 47 % of the camel's cells with ``cnlf``
under ``condtrack compare``'s defaults (the CLF, which draws nothing, on none;
README, "Golden files in CI", has the commands and every shared set), and
tracking a subset of the queries moved the points kept (tests/test_cnlf.py).

:class:`PointDraws` makes every draw a function of (the pass's key, the frame,
the use, the point's id, the draw's number) alone: a counter-based generator,
splitmix64 (Steele, Lea & Flood, OOPSLA 2014: a Weyl sequence through a 64-bit
mixing function; its output passes BigCrush) seeded per point, computed for all
points at once with numpy's uint64 arithmetic. numpy's own bit generators take
one key each, which would mean one generator per point and frame, a Python loop
over points. Normal draws are Box-Muller pairs of its uniforms. The pass's key
is the first draw of the pass's ``rng`` (``--seed``; the backward pass has its own).
"""

from __future__ import annotations

import numpy as np

#: Uses of the draws: particles drawn around a (re)started point, the proposal's draws (eq. 11), the resampling's
#: uniform.
START, PROPOSAL, RESAMPLING = 0, 1, 2

#: splitmix64's increment, 2^64 / golden ratio.
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64's mixing function of the uint64 array ``x``, in place (a bijection; wraps modulo 2^64)."""
    for shift, factor in ((30, 0xBF58476D1CE4E5B9), (27, 0x94D049BB133111EB)):
        x ^= x >> np.uint64(shift)
        x *= np.uint64(factor)
    x ^= x >> np.uint64(31)
    return x


class PointDraws:
    """Uniform and standard normal draws keyed by (pass, frame, use, point id, draw number)."""

    def __init__(self, rng: np.random.Generator, point_ids: np.ndarray):
        """rng: the pass's source of random draws (one 63-bit integer from it keys every later draw); point_ids (P,)
        int64: the queries' ids, which key each point's draws."""
        self.key = rng.integers(2**63, size=1).astype(np.uint64)
        self.ids = np.ascontiguousarray(point_ids, dtype=np.int64).view(np.uint64)

    def _bits(self, frame: int, use: int, index: np.ndarray, count: int) -> np.ndarray:
        """(n, count) uint64 random words of points ``index`` (n,): splitmix64's first ``count`` outputs from each
        point's seed, a mix of the key, ``frame``, ``use`` and the point's id."""
        counters = np.array([frame + 1, use + 1], dtype=np.uint64) * _GOLDEN  # arrays: numpy wraps them silently
        seed = _mix(_mix(self.key + counters[:1]) ^ counters[1:])  # (1,)
        seeds = _mix(seed ^ _mix(self.ids[index] + _GOLDEN))  # (n,)
        steps = _GOLDEN * np.arange(1, count + 1, dtype=np.uint64)  # the Weyl sequence's states
        return _mix(seeds[:, None] + steps[None, :])

    def uniform(self, frame: int, use: int, index: np.ndarray, count: int = 1) -> np.ndarray:
        """(n, count) uniform draws in [0, 1) of the points ``index`` (n,) on ``frame`` for ``use`` (53-bit)."""
        return (self._bits(frame, use, index, count) >> np.uint64(11)) * (1.0 / 2**53)

    def normal_pairs(self, frame: int, use: int, index: np.ndarray, count: int) -> np.ndarray:
        """(n, count, 2) independent standard normal draws of the points ``index`` (n,) on ``frame`` for ``use``:
        Box-Muller, r = sqrt(-2 ln(1 - u1)), angle 2 pi u2, from two uniforms per pair."""
        u = self.uniform(frame, use, index, 2 * count).reshape(len(index), count, 2)
        radius = np.sqrt(-2.0 * np.log1p(-u[..., 0]))
        angle = 2.0 * np.pi * u[..., 1]
        return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=-1)
