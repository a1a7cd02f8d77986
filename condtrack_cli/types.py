"""The arrays that flow between stages, their shapes and the pixel convention.

Pixel convention (every position in this package): x to the right, y down, in
pixels, origin (0, 0) at the *centre* of the top-left pixel, so pixel (row i,
column j) covers [j-0.5, j+0.5] x [i-0.5, i+0.5]. This is OpenCV's convention.

Shapes use P = points, F = frames, N = particles.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any

import numpy as np


def same_value(a: Any, b: Any) -> bool:
    """``a`` and ``b`` hold the same values: arrays of one dtype and shape with equal elements (NaN equal to NaN),
    mappings with the same keys and same values, else ``==``."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape
                and bool(np.array_equal(a, b, equal_nan=a.dtype.kind in "fc")))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_value(a[key], b[key]) for key in a)
    return bool(a == b)


class ArrayFields:
    """``==`` for a dataclass of arrays: the same class and every field the same value (``same_value``), where the
    dataclass's own ``==`` compared tuples of arrays and raised numpy's "truth value ... is ambiguous"."""

    def __eq__(self, other: object) -> bool:
        if other.__class__ is not self.__class__:
            return NotImplemented
        return all(same_value(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    __hash__ = None  # equal by value, and mutable arrays inside: not hashable


@dataclass(frozen=True)
class SequenceInfo:
    """What is known of an input before its frames are read."""

    input: str
    width: int
    height: int
    n_frames: int
    fps: float  #: frames per second; 0.0 when the input has no timing (a folder)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """(...) bool: which of the (..., 2) positions ``xy`` lie inside the frame, [-0.5, W-0.5] x [-0.5, H-0.5]
        (the pixel convention above); False for NaN."""
        x, y = xy[..., 0], xy[..., 1]
        with np.errstate(invalid="ignore"):
            return (x >= -0.5) & (x <= self.width - 0.5) & (y >= -0.5) & (y <= self.height - 0.5)


@dataclass(frozen=True, eq=False)
class Queries(ArrayFields):
    """Points to track, each from its own frame.

    point_id: (P,) int64; frame: (P,) int64 query frame; xy: (P, 2) float64 pixels.
    """

    point_id: np.ndarray
    frame: np.ndarray
    xy: np.ndarray

    def __post_init__(self) -> None:
        p = len(self.point_id)
        if self.frame.shape != (p,) or self.xy.shape != (p, 2):
            raise ValueError("Queries arrays disagree in shape")

    def __len__(self) -> int:
        return len(self.point_id)


@dataclass(frozen=True)
class Pyramid:
    """A frame's Gaussian pyramid with its gradients.

    base: (H, W) float32, the frame smoothed by a Gaussian of std ``motion.pyramid.PRESMOOTH_SIGMA``
    px (level 0). levels: finest first, (h_l, w_l, 3) float32 [I, dI/dx, dI/dy]
    in grey levels and grey per pixel of that level (3x3 Sobel / 8).
    """

    base: np.ndarray
    levels: list[np.ndarray]


@dataclass
class Frame:
    """One frame as stages see it.

    index: position in the sequence (0-based); image: (H, W) uint8 grey.
    pyramid: the frame's Gaussian pyramid with gradients, None until a motion
    estimate builds it (``motion.pyramid.frame_pyramid``); kept with the frame
    so that the pairs k-1 -> k and k -> k+1 build it once.
    """

    index: int
    image: np.ndarray
    pyramid: Pyramid | None = None

    @cached_property
    def gray(self) -> np.ndarray:
        """(H, W) float32 grey levels in [0, 255]."""
        return self.image.astype(np.float32)


@dataclass(frozen=True)
class FrameEstimate:
    """What a tracker reports for all P points on one frame.

    xy: (P, 2) position, NaN where the point has no state yet.
    cov: (P, 2, 2) posterior covariance in px^2; NaN when the method has none.
    dof: (P,) degrees of freedom nu > 2 of the row's bivariate Student-t predictive
       distribution (covariance ``cov``); inf: Gaussian.
    visible: (P,) bool.
    z: (P, 2) raw measurement (NaN where none was made).
    R: (P, 2, 2) measurement covariance in px^2; +inf on the diagonal when the
       correlation surface carried no information, NaN where no measurement.
    method: (P,) int8 code of the filter that produced the row, an index into
       ``registry.method_codes()`` (-1 where the point has no state).
    """

    xy: np.ndarray
    cov: np.ndarray
    dof: np.ndarray
    visible: np.ndarray
    z: np.ndarray
    R: np.ndarray
    method: np.ndarray


@dataclass(frozen=True, eq=False)
class Tracks(ArrayFields):
    """A whole tracking result, as written to CSV and HDF5.

    xy: (P, F, 2) float64, NaN where the point has no state.
    cov: (P, F, 2, 2) float64 px^2, NaN where undefined, inf where unbounded.
    dof: (P, F) float64 degrees of freedom nu > 2 of each row's Student-t
       predictive distribution (``FrameEstimate``); inf: Gaussian; NaN where the
       point has no state.
    visible: (P, F) bool.
    method: (P, F) int8 index into ``registry.method_codes()``, -1 where no state.
    z, R: raw measurements, (P, F, 2) and (P, F, 2, 2), as in ``FrameEstimate``.
    extras: optional HDF5 datasets by path, written when configured:
       ``particles/xy`` (P, F, N, 2) float32, the CNLF's particles (NaN where
       the point is not on the CNLF); ``segmentation`` (F - 1, H, W) uint8,
       255 x the robust weight of the global fit from frame k to k + 1 on frame
       k's grid (the pixels that follow the dominant motion).
    trackability: (P,) float64 Shi-Tomasi score of each query at its query frame, (grey/px)^2
       (``detect/trackability.py``); NaN where unknown (filled so when not given).
    """

    queries: Queries
    xy: np.ndarray
    cov: np.ndarray
    dof: np.ndarray
    visible: np.ndarray
    method: np.ndarray
    z: np.ndarray
    R: np.ndarray
    extras: dict = field(default_factory=dict)
    trackability: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.trackability is None:
            object.__setattr__(self, "trackability", np.full(len(self.queries), np.nan))

    @property
    def has_state(self) -> np.ndarray:
        """(P, F) bool: rows that exist in the long CSV."""
        return np.isfinite(self.xy).all(axis=-1)

    def _main_codes(self) -> tuple[tuple[str, ...], np.ndarray]:
        """The method names (``registry.method_codes()`` and "" for no state) and (P,) the index into them of the
        method that produced most of each point's frames."""
        from condtrack_cli.registry import method_codes

        codes = method_codes()
        counts = (self.method[:, :, None] == np.arange(len(codes))).sum(axis=1)  # (P, M)
        return codes + ("",), np.where(counts.any(axis=1), counts.argmax(axis=1), len(codes))

    def point_methods(self) -> list[str]:
        """(P,) the method that produced most of each point's frames."""
        names, best = self._main_codes()
        return list(np.array(names, dtype=object)[best])

    def method_split(self) -> str:
        """How many points each method produced most of, in code order: ``"clf 5, cnlf 1"`` ("no state" last)."""
        names, best = self._main_codes()
        per_method = np.bincount(best, minlength=len(names))
        return ", ".join(f"{name or 'no state'} {count}" for name, count in zip(names, per_method) if count)
