"""Acquisition noise of a frame (Immerkær on its flattest quarter) and the noise-only residual threshold of eq. (10)."""

from __future__ import annotations

import cv2
import numpy as np

from condtrack_cli.special import normal_quantile


#: Std of the rounding of grey levels to integers (grey levels): the least noise of an 8-bit frame.
_QUANTISATION_STD = 1.0 / np.sqrt(12.0)


#: Immerkær's (1996) operator: the difference of two Laplacians; zero on planes, sum of squares 36.
_IMMERKAER = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def estimate_noise_sigma(gray: np.ndarray) -> float:
    """Acquisition noise std of one frame (grey levels).

    Immerkær's operator N = [[1,-2,1],[-2,4,-2],[1,-2,1]] (J. Immerkær, "Fast noise
    variance estimation", CVIU 64(2), 1996) cancels planes and leaves 36 sigma^2 of
    white noise. Immerkær averages |I * N| over the whole frame, which counts
    texture and edges as noise (2x too high on a textured photograph); here the
    response is read only where the image has the least structure (the quarter of
    pixels with the smallest 7 x 7 mean squared gradient of the image smoothed by a
    Gaussian of std 2 px, smoothing that leaves the structure measure free of the
    noise), and its scale is the median absolute value (robust to the remaining
    edges): sigma = median |I * N| / (0.6745 * 6). Measured: sigma = 3 added to
    the camera, coffee and astronaut photographs reads 3.0-3.3 (whole-frame
    Immerkær: 4.2-6.2); a frame that is all texture (gravel) still reads high.
    The result is at least 1/sqrt(12), the rounding noise of 8-bit frames, so that
    a noise-free synthetic frame does not give 0.
    """
    image = np.asarray(gray, np.float32)
    if min(image.shape) < 3:
        raise ValueError(f"need a frame of at least 3 x 3 pixels, got {image.shape}")
    response = cv2.filter2D(image, cv2.CV_32F, _IMMERKAER, borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    smooth = cv2.GaussianBlur(image, (0, 0), 2.0)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    structure = cv2.boxFilter(gx * gx + gy * gy, -1, (7, 7), borderType=cv2.BORDER_REFLECT)[1:-1, 1:-1]
    flattest = structure <= np.quantile(structure, 0.25)
    sigma = float(np.median(np.abs(response[flattest])) / (normal_quantile(0.75) * 6.0))
    return max(sigma, _QUANTISATION_STD)


def noise_threshold(sigma: float, m: int, alpha: float) -> float:
    """Largest residual consistent with noise at level ``alpha`` (grey levels^2), eq. (10).

    sqrt(2 r / sigma_d^2) - sqrt(2 m) ~ N(0, 1) with sigma_d^2 = 2 sigma^2 and m
    template pixels; r is consistent with noise when that is below the (1 - alpha)
    quantile q, i.e. r < sigma_d^2 (q + sqrt(2 m))^2 / 2.
    """
    sigma_d2 = 2.0 * sigma**2
    q = normal_quantile(1.0 - alpha)
    return sigma_d2 * (q + np.sqrt(2.0 * m)) ** 2 / 2.0  # eq. (10) solved for r
