"""Layers of a synthetic scene: shapes with signed distances, textured layers, the photographic background, rendering."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from typing import Protocol

import cv2
import numpy as np
from scipy import ndimage

from condtrack_cli.frames.synthetic.affine import _apply, _compose, _invert

SOURCE_MARGIN = 3  #: source pixels kept between a frame's footprint and the photo edge


class _Shape(Protocol):
    def sdf(self, u: np.ndarray) -> np.ndarray:
        """Signed distance in source pixels (positive inside) at points u (..., 2) -> (...)."""


@dataclass(frozen=True)
class _Disk:
    """Disk of ``radius`` around ``centre`` (2,), in source pixels."""

    centre: np.ndarray
    radius: float

    def sdf(self, u: np.ndarray) -> np.ndarray:
        return self.radius - np.hypot(u[..., 0] - self.centre[0], u[..., 1] - self.centre[1])


@dataclass(frozen=True)
class _Band:
    """Vertical band, unbounded in y, with wavy edges (a tree trunk), in source pixels.

    Inside: left + a sin(w y + phase_l) < x < right + a sin(w y + phase_r), w = 2 pi / wavelength.
    The distance is the horizontal one divided by the edge's slope factor.
    """

    left: float
    right: float
    amplitude: float
    wavelength: float
    phase_left: float
    phase_right: float

    def sdf(self, u: np.ndarray) -> np.ndarray:
        x, y = u[..., 0], u[..., 1]
        w = 2 * np.pi / self.wavelength
        aw = self.amplitude * w
        to_left = (x - self.left - self.amplitude * np.sin(w * y + self.phase_left)) / np.hypot(
            1.0, aw * np.cos(w * y + self.phase_left)
        )
        to_right = (self.right + self.amplitude * np.sin(w * y + self.phase_right) - x) / np.hypot(
            1.0, aw * np.cos(w * y + self.phase_right)
        )
        return np.minimum(to_left, to_right)


@dataclass(frozen=True)
class _Rect:
    """Axis-aligned rectangle [left, right] x [top, bottom] (a card), in source pixels.

    The distance is the smallest to the four sides' lines: exact inside and along the
    edges, which is all the anti-aliased mask and the margins read.
    """

    left: float
    right: float
    top: float
    bottom: float

    def sdf(self, u: np.ndarray) -> np.ndarray:
        x, y = u[..., 0], u[..., 1]
        return np.minimum(np.minimum(x - self.left, self.right - x), np.minimum(y - self.top, self.bottom - y))


@dataclass(frozen=True)
class _Layer:
    """A source image moved into the frames.

    coeffs: (h, w) cubic B-spline coefficients of the source image (mirror boundary).
    to_frame: (F, 2, 3) map from source pixels to frame-k pixels (rigid for objects).
    shape: the layer's support in source pixels; None for the background (everywhere).
    """

    coeffs: np.ndarray
    to_frame: np.ndarray
    shape: _Shape | None = None

    @property
    def maps(self) -> np.ndarray:
        """(F, 2, 3) frame 0 -> frame k maps of the layer's points."""
        return _compose(self.to_frame, _invert(self.to_frame[0]))

    def sample(self, u: np.ndarray) -> np.ndarray:
        """Source intensities at source positions u (N, 2) -> (N,) float64."""
        return ndimage.map_coordinates(
            self.coeffs, [u[:, 1], u[:, 0]], order=3, prefilter=False, mode="mirror", output=np.float64
        )

    def sdf(self, x: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Signed distance (px, positive inside) of an object layer at frame positions x (N, K, 2) in frames (K,) -> (N, K)."""
        return self.shape.sdf(_apply(_invert(self.to_frame[frames]), x))


@lru_cache(maxsize=None)
def _coeffs(name: str) -> np.ndarray:
    """Spline coefficients (h, w) of the shipped 8-bit grey asset ``name``.png (read-only, cached)."""
    data = (resources.files("condtrack_cli.frames") / "assets" / f"{name}.png").read_bytes()
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    coeffs = ndimage.spline_filter(image.astype(np.float64), order=3, mode="mirror")
    coeffs.flags.writeable = False
    return coeffs


def _background(photo: str, camera: np.ndarray, size: tuple[int, int], rng: np.random.Generator,
                region: tuple[float, float, float, float] | None = None) -> _Layer:
    """Background layer: ``photo`` moved by the camera maps (F, 2, 3) (frame 0 -> frame k).

    The photograph is placed (at a seeded random offset, magnified only if it is too
    small) so that every frame's footprint lies SOURCE_MARGIN pixels inside it, or inside
    ``region`` (left, top, right, bottom, source pixels) when given.
    """
    coeffs = _coeffs(photo)
    ph, pw = coeffs.shape
    w, h = size
    left, top, right, bottom = region or (0.0, 0.0, pw - 1.0, ph - 1.0)
    corners = np.array([[0.0, 0.0], [w - 1.0, 0.0], [0.0, h - 1.0], [w - 1.0, h - 1.0]])
    footprint = _apply(_invert(camera)[:, None], corners[None])  # (F, 4, 2) in frame-0 pixels
    low, high = footprint.min(axis=(0, 1)), footprint.max(axis=(0, 1))
    room = np.array([right - left, bottom - top]) - 2 * SOURCE_MARGIN
    scale = max(1.0, *((high - low) / room))
    slack = np.maximum(room - (high - low) / scale, 0.0)  # 0 along the side that set the scale
    offset = np.array([left, top]) + SOURCE_MARGIN - low / scale + rng.uniform(0.0, 1.0, 2) * slack  # source = frame0 / scale + offset
    to_frame0 = np.array([[scale, 0.0, -scale * offset[0]], [0.0, scale, -scale * offset[1]]])
    return _Layer(coeffs, _compose(camera, to_frame0))



def _grid(size: tuple[int, int]) -> np.ndarray:
    """(H * W, 2) pixel-centre positions (x, y) in row-major order."""
    w, h = size
    return np.stack(np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float)), axis=-1).reshape(-1, 2)


def _render(layers: list[_Layer], size: tuple[int, int], photometry: np.ndarray, noise: float, rng) -> np.ndarray:
    """Frames (F, H, W) uint8; photometry (F, 3) holds contrast, bias and blur sigma per frame."""
    w, h = size
    grid = _grid(size)
    n_frames = len(photometry)
    frames = np.empty((n_frames, h, w), np.uint8)
    bottom = layers[0]
    for k, (contrast, bias, blur) in enumerate(photometry):
        image = bottom.sample(_apply(_invert(bottom.to_frame[k]), grid))
        for lay in layers[1:]:
            u = _apply(_invert(lay.to_frame[k]), grid)
            alpha = np.clip(lay.shape.sdf(u) + 0.5, 0.0, 1.0)
            hit = alpha > 0
            image[hit] += alpha[hit] * (lay.sample(u[hit]) - image[hit])
        image = 128.0 + contrast * (image.reshape(h, w) - 128.0) + bias
        image = cv2.GaussianBlur(image, (0, 0), blur, borderType=cv2.BORDER_REFLECT) if blur > 0 else image
        frames[k] = np.clip(np.rint(image + rng.normal(0.0, noise, (h, w))), 0, 255)
    return frames


