"""The photometric check of the ``rotation`` agent: whether a view *is* the target, in colour.
:func:`photometric_template` (downsampled, blurred, zero-mean, unit-norm image), :func:`photometric_score`
(colour normalised cross-correlation of two templates) and :func:`mean_chromaticity` (the mean colour's
chromaticity); the agent stops on a candidate only when both agree, and refines its last degree by
climbing the score."""

from __future__ import annotations

import cv2
import numpy as np

from findview_baselines.agents.base import chw_to_hwc

__all__ = ["VERIFY_SCALE", "VERIFY_SIGMA", "photometric_template", "mean_chromaticity", "photometric_score"]

VERIFY_SCALE = 4  # the check compares images downsampled by this factor (area average) ...
VERIFY_SIGMA = 1.0  # ... then blurred with this Gaussian sigma (pixels of the downsampled image)


def photometric_template(image: np.ndarray, scale: int = VERIFY_SCALE, sigma: float = VERIFY_SIGMA) -> np.ndarray:
    """The ``(3, H, W)`` uint8 RGB image as the check sees it: downsampled ``scale`` times (area
    average), blurred (``sigma``, pixels of the downsampled image), per-channel mean removed, scaled to
    unit norm over all channels. Returns ``(H / scale, W / scale, 3)`` float32 (zeros for a flat image)."""
    hwc = chw_to_hwc(image)
    h, w = hwc.shape[:2]
    small = cv2.resize(hwc, (max(1, w // scale), max(1, h // scale)), interpolation=cv2.INTER_AREA)
    x = cv2.GaussianBlur(small.astype(np.float32), (0, 0), sigma)
    x -= x.reshape(-1, 3).mean(axis=0)
    n = float(np.sqrt((x * x).sum()))
    return x / n if n > 1e-3 else np.zeros_like(x)


def mean_chromaticity(image: np.ndarray) -> np.ndarray:
    """Chromaticity ``(r, g, b) / (r + g + b)`` of the mean colour of a ``(3, H, W)`` uint8 RGB image,
    ``(3,)`` float64 (grey: ``1/3`` each; a flat black image counts as grey). A gain on all channels,
    contrast changes about the mean, blur and zero-mean noise leave it (almost) unchanged."""
    m = image.reshape(3, -1).mean(axis=1, dtype=np.float64)
    t = float(m.sum())
    return m / t if t > 1e-6 else np.full(3, 1.0 / 3.0)


def photometric_score(a: np.ndarray, b: np.ndarray) -> float:
    """Colour zero-mean normalised cross-correlation of two :func:`photometric_template` outputs, in
    ``[-1, 1]`` (1: the same picture up to a gain and a per-channel offset).

    The three channels are correlated together (one norm over all of them): the same structure in
    other colours scores low (the channels that carry it differ), while blur and noise (removed by the
    downsampling and the blur), brightness and contrast changes (a gain and offsets) keep a high score.
    """
    return float((a * b).sum())
