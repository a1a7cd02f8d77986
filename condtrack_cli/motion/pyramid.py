"""Gaussian pyramids with gradients, built once per frame and shared by the global and the local motion."""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.types import Frame, Pyramid


#: Std (px) of the Gaussian smoothing both frames before estimation; see the module docstring.
PRESMOOTH_SIGMA = 1.0


#: Smallest side (px) of the coarsest pyramid level: below it the level is too
#: blurred to tell a textured object's motion from the background's.
MIN_COARSE_SIDE = 64


def build_pyramid(gray: np.ndarray, levels: int) -> Pyramid:
    """Gaussian pyramid (``cv2.pyrDown``) of a (H, W) frame, with gradients, ``levels`` deep."""
    return deepen(Pyramid(cv2.GaussianBlur(np.asarray(gray, np.float32), (0, 0), PRESMOOTH_SIGMA), []), levels)


def deepen(pyramid: Pyramid, levels: int) -> Pyramid:
    """``pyramid`` with coarser levels appended (``cv2.pyrDown`` of the coarsest image) until ``levels`` deep."""
    stacks = list(pyramid.levels)
    image = stacks[-1][:, :, 0] if stacks else pyramid.base
    for level in range(len(stacks), levels):
        if level:
            image = cv2.pyrDown(image)
        gx = cv2.Sobel(image, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
        gy = cv2.Sobel(image, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
        stacks.append(cv2.merge((image, gx, gy)))
    return Pyramid(pyramid.base, stacks)


def usable_levels(shape: tuple[int, int], levels: int) -> int:
    """``levels`` capped so that the coarsest level's shorter side is >= MIN_COARSE_SIDE px."""
    return min(levels, 1 + max(0, int(np.log2(min(shape) / MIN_COARSE_SIDE))))


def frame_pyramid(frame: Frame, levels: int) -> Pyramid:
    """``build_pyramid`` of ``frame.gray``, ``levels`` deep, kept in ``frame.pyramid`` for the next frame pair."""
    if frame.pyramid is None:
        frame.pyramid = build_pyramid(frame.gray, levels)
    elif len(frame.pyramid.levels) < levels:  # a deeper one asked for later: the levels built are kept
        frame.pyramid = deepen(frame.pyramid, levels)
    return Pyramid(frame.pyramid.base, frame.pyramid.levels[:levels])
