"""The photometric side of the ``rotation`` agent: whether a view *is* the target, robust to what a
corrupted target does to intensities.

Fog and contrast corruptions keep a picture's structure and change its intensities: contrast scales the
deviations from each channel's mean (by 0.2 at severity 3), fog adds a smooth grey "plasma" field and
scales everything down (to about 0.3 at severity 3). Raw gray levels then fool the feature detector
(too few keypoints pass its contrast threshold) and a plain correlation (the fog field is structure of
its own). So:

- :func:`normalize_contrast` / :func:`detection_image`: local contrast normalisation (subtract a
  Gaussian local mean, divide by the local standard deviation, floored relative to the image's own
  contrast) of a gray image; the agent detects keypoints on it, for the view and the target alike;
- :func:`structure_template` / :func:`structure_score`: the correlation of the locally normalised gray
  images (the content check and the score the one-degree refinement climbs);
- :func:`colour_template` (a high-passed :func:`photometric_template`): the colour correlation without
  the smooth fog field; the same structure in other colours (a mirror face of another colour) scores low;
- :func:`opponent_template`: the high-passed layout of the colour differences ``(R - G, G - B)``; a
  grey fog field cancels in them and fog / contrast only scale them, so the target's own view scores
  about 1 under fog and contrast, where the colour correlation of a fogged view can fall to 0.2;
- :func:`opponent_mean` / :func:`hue_residual`: the mean colour as opponent differences ``(R - G,
  G - B)``, which a grey fog field cancels and a contrast change keeps; two views whose mean colours
  are not the same up to a gain are different surfaces (the colour check);
- :func:`photometric_template` / :func:`photometric_score` (colour correlation of blurred images) and
  :func:`mean_chromaticity`: the older colour checks, kept as helpers."""

from __future__ import annotations

import cv2
import numpy as np

from findview_baselines.agents.base import chw_to_hwc

__all__ = [
    "VERIFY_SCALE",
    "VERIFY_SIGMA",
    "LCN_SIGMA",
    "photometric_template",
    "mean_chromaticity",
    "photometric_score",
    "normalize_contrast",
    "detection_image",
    "colour_template",
    "structure_template",
    "structure_score",
    "opponent_mean",
    "hue_residual",
    "opponent_template",
]

VERIFY_SCALE = 4  # the check compares images downsampled by this factor (area average) ...
VERIFY_SIGMA = 1.0  # ... then blurred with this Gaussian sigma (pixels of the downsampled image)
LCN_SIGMA = 4.0  # local contrast normalisation before keypoint detection: Gaussian window, full-size pixels
LCN_FLOOR = 0.1  # local standard deviations are floored at this fraction of the image's global one
STRUCT_SCALE = 2  # the content check normalises at 1/2 size ...
STRUCT_SIGMA = 6.0  # ... with this window (pixels at 1/2 size), then compares at 1/4 size (blur 1 pixel)


def _downsampled(hwc: np.ndarray, scale: int) -> np.ndarray:
    """``(H, W, C)`` -> ``(H / scale, W / scale, C)`` by area averaging (at least one pixel per axis)."""
    h, w = hwc.shape[:2]
    return cv2.resize(hwc, (max(1, w // scale), max(1, h // scale)), interpolation=cv2.INTER_AREA)


def _unit(x: np.ndarray) -> np.ndarray:
    """``(H, W, C)`` float32 with each channel's mean removed (in place) and the joint unit norm; zeros when
    nothing is left (a flat image)."""
    x -= x.reshape(-1, x.shape[-1]).mean(axis=0)
    n = float(np.sqrt((x * x).sum()))
    return x / n if n > 1e-3 else np.zeros_like(x)


def photometric_template(image: np.ndarray, scale: int = VERIFY_SCALE, sigma: float = VERIFY_SIGMA) -> np.ndarray:
    """The ``(3, H, W)`` uint8 RGB image as the check sees it: downsampled ``scale`` times (area
    average), blurred (``sigma``, pixels of the downsampled image), per-channel mean removed, scaled to
    unit norm over all channels. Returns ``(H / scale, W / scale, 3)`` float32 (zeros for a flat image)."""
    x = cv2.GaussianBlur(_downsampled(chw_to_hwc(image), scale).astype(np.float32), (0, 0), sigma)
    return _unit(x)


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


def normalize_contrast(gray: np.ndarray, sigma: float = LCN_SIGMA, floor: float = LCN_FLOOR) -> np.ndarray:
    """Local contrast normalisation of a ``(H, W)`` gray image (any dtype): ``(g - mu) / sqrt(var + f^2)``
    with ``mu`` and ``var`` the Gaussian-weighted local mean and variance (window ``sigma`` pixels) and
    ``f = floor x`` the global RMS of ``g - mu``. Invariant to a gain and an offset of the image (the
    floor scales with the image), and to smooth additive fields much wider than ``sigma`` (fog).
    Returns ``(H, W)`` float32, about unit variance where there is texture, 0 for a flat image."""
    g = np.asarray(gray, dtype=np.float32)
    hp = g - cv2.GaussianBlur(g, (0, 0), sigma)
    var = cv2.GaussianBlur(hp * hp, (0, 0), sigma)
    f = floor * float(np.sqrt(np.mean(hp * hp))) + 1e-4
    return hp / np.sqrt(var + f * f)


def detection_image(gray: np.ndarray, sigma: float = LCN_SIGMA) -> np.ndarray:
    """The ``(H, W)`` uint8 image keypoints are detected on: :func:`normalize_contrast` (window ``sigma``
    pixels) mapped to ``128 + 40 z`` and clipped to [0, 255]. A low-contrast or fogged image gets as many
    keypoints as a clean one, at the same places."""
    z = normalize_contrast(gray, sigma)
    return np.clip(z * 40.0 + 128.5, 0.0, 255.0).astype(np.uint8)


def structure_template(
    image: np.ndarray, scale: int = STRUCT_SCALE, sigma: float = STRUCT_SIGMA, out: int = 2, blur: float = 1.0
) -> np.ndarray:
    """The ``(3, H, W)`` uint8 RGB image as the content check sees it: gray, downsampled ``scale`` times
    (area average), :func:`normalize_contrast` (window ``sigma``, pixels at that size), downsampled
    ``out`` more times, blurred (``blur`` pixels), zero mean, unit norm. Returns float32 ``(H / (scale
    out), W / (scale out))``; zeros for a flat image."""
    g = chw_to_hwc(image).astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    if scale > 1:
        g = _downsampled(g, scale)
    z = normalize_contrast(g, sigma)
    if out > 1:
        z = _downsampled(z, out)
    if blur > 0:
        z = cv2.GaussianBlur(z, (0, 0), blur)
    z = z - float(z.mean())
    n = float(np.sqrt((z * z).sum()))
    return z / n if n > 1e-6 else np.zeros_like(z)


#: normalised cross-correlation of two :func:`structure_template` outputs, in ``[-1, 1]`` (1: the same picture up to
#: a gain, an offset and a smooth additive field): the same dot product of unit templates as :func:`photometric_score`
structure_score = photometric_score


def opponent_mean(image: np.ndarray) -> np.ndarray:
    """Mean opponent colour ``(mean(R - G), mean(G - B))`` of a ``(3, H, W)`` uint8 RGB image, ``(2,)``
    float64 grey levels. A grey additive field (fog) leaves it unchanged up to the common gain; a
    contrast change about the channel means leaves it unchanged."""
    m = image.reshape(3, -1).mean(axis=1, dtype=np.float64)
    return np.array([m[0] - m[1], m[1] - m[2]])


def hue_residual(target: np.ndarray, view: np.ndarray, gain: tuple[float, float] = (0.2, 4.0)) -> float:
    """How far two :func:`opponent_mean` vectors are from being the same colour up to a gain:
    ``min |target - k view|`` over ``k`` in ``gain`` (grey levels). 0 for the same colour, scaled
    (fog, brightness, saturation) or not; large for another hue, e.g. a yellow surface against a green
    one, whatever their brightness."""
    t = np.asarray(target, np.float64)
    v = np.asarray(view, np.float64)
    vv = float(v @ v)
    k = float(t @ v) / vv if vv > 1e-12 else 0.0
    k = min(max(k, gain[0]), gain[1])
    return float(np.linalg.norm(t - k * v))


def colour_template(image: np.ndarray, scale: int = VERIFY_SCALE, highpass: float = 4.0) -> np.ndarray:
    """:func:`photometric_template` of the ``(3, H, W)`` uint8 RGB image with each channel high-passed
    (minus its Gaussian blur of ``highpass`` pixels at the downsampled size) before the mean removal and
    the joint unit norm: smooth additive fields (fog) drop out, colour edges stay. Compare two with
    :func:`photometric_score`. Returns ``(H / scale, W / scale, 3)`` float32 (zeros for a flat image)."""
    x = cv2.GaussianBlur(_downsampled(chw_to_hwc(image), scale).astype(np.float32), (0, 0), VERIFY_SIGMA)
    return _unit(x - cv2.GaussianBlur(x, (0, 0), highpass))


def opponent_template(image: np.ndarray, scale: int = VERIFY_SCALE, highpass: float = 4.0) -> np.ndarray:
    """The colour-difference layout of a ``(3, H, W)`` uint8 RGB image: the opponent channels ``(R - G,
    G - B)``, downsampled ``scale`` times (area average), blurred (``VERIFY_SIGMA``), high-passed (minus
    their Gaussian blur of ``highpass`` pixels), per-channel mean removed, joint unit norm. Compare two
    with :func:`photometric_score`. Returns ``(H / scale, W / scale, 2)`` float32 (zeros for a grey image).

    A grey additive field (fog: the same plasma on every channel) cancels in the differences, and fog's
    rescaling, a contrast change about the channel means and brightness gains only scale them: the
    target's own view scores about 1 under fog and contrast (0.999 or more on the val panoramas), one
    degree off about 0.9, another place or the mirror face of the test cube (the same edges in other
    colours) 0.6 at most. Noise, JPEG's chroma subsampling and blur lower it for the right view too, so
    it only ever *adds* evidence (see ``RotationAgent.verify``)."""
    small = _downsampled(chw_to_hwc(image).astype(np.float32), scale)  # float first: fog leaves small differences
    x = np.stack([small[..., 0] - small[..., 1], small[..., 1] - small[..., 2]], axis=-1)
    x = cv2.GaussianBlur(x, (0, 0), VERIFY_SIGMA)
    return _unit(x - cv2.GaussianBlur(x, (0, 0), highpass))
