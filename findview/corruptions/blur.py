"""Blur corruptions: motion, defocus, glass and Gaussian blur (reference severity tables)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ._common import gaussian_blur as _gaussian_blur
from ._common import gaussian_kernel1d, motion_blur as _motion_blur, uniform

# (radius in taps, sigma in taps): 2 * radius + 1 shifted copies with one-sided Gaussian weights
MOTION_BLUR = ((10, 3), (15, 5), (15, 8), (15, 12), (20, 15))
# (disk radius in pixels, anti-alias blur sigma in pixels)
DEFOCUS_BLUR = ((3, 0.1), (4, 0.5), (6, 0.5), (8, 0.5), (10, 0.5))
# (Gaussian sigma in pixels, maximal displacement in pixels, iterations)
GLASS_BLUR = ((0.7, 1, 2), (0.9, 2, 1), (1, 2, 3), (1.1, 3, 2), (1.5, 4, 2))
# Gaussian sigma in pixels
GAUSSIAN_BLUR = (1, 2, 3, 4, 6)


def motion_blur(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Blur along one random direction per image, uniform in [-45, 45) degrees from the x axis."""
    radius, sigma = MOTION_BLUR[severity - 1]
    angle = uniform((x.shape[0],), -45.0, 45.0, g, x.device)
    return _motion_blur(x, radius, sigma, angle)


def disk_kernel(radius: int, alias_blur: float) -> np.ndarray:
    """The reference's anti-aliased disk (float32, sums to ~1).

    A binary disk of ``radius`` pixels on a ``17 x 17`` grid (radius <= 8) or a
    ``(2 radius + 1)`` square grid, normalised, then Gaussian-blurred (3x3 resp. 5x5 kernel,
    ``alias_blur`` sigma, mirrored borders without repeating the edge).
    """
    half = 8 if radius <= 8 else radius
    ksize = 3 if radius <= 8 else 5
    t = np.arange(-half, half + 1)
    yy, xx = np.meshgrid(t, t, indexing="ij")
    disk = ((xx**2 + yy**2) <= radius**2).astype(np.float32)
    disk /= disk.sum()
    k1 = gaussian_kernel1d(alias_blur, ksize // 2).astype(np.float32)
    r = ksize // 2
    pad = np.pad(disk, r, mode="reflect")
    rows = sum(k1[i] * pad[:, i : i + disk.shape[1]] for i in range(ksize))
    out = sum(k1[i] * rows[i : i + disk.shape[0], :] for i in range(ksize))
    return out.astype(np.float32)


def defocus_blur(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Convolve every channel with an anti-aliased disk (mirrored borders, edge not repeated).

    No randomness. Computed with FFTs of the padded image, whose circular wrap-around only touches
    the padding that is cropped away.
    """
    radius, alias = DEFOCUS_BLUR[severity - 1]
    k = torch.as_tensor(disk_kernel(radius, alias), dtype=torch.float32, device=x.device)
    size = k.shape[0]
    r = size // 2
    _, _, h, w = x.shape
    xp = F.pad(x, (r, r, r, r), mode="reflect")
    hp, wp = h + 2 * r, w + 2 * r
    kf = torch.fft.rfft2(k.flip(0, 1), s=(hp, wp))
    y = torch.fft.irfft2(torch.fft.rfft2(xp) * kf, s=(hp, wp))
    return y[:, :, size - 1 :, size - 1 :].to(x.dtype)


def glass_shuffle_sources(offsets: torch.Tensor, height: int, width: int, delta: int) -> torch.Tensor:
    """Where each pixel's value comes from after one pass of the reference's pixel 'swap'.

    The reference visits pixels ``(h, w)`` for ``h`` from ``H - delta`` down to ``delta + 1`` and,
    within a row, ``w`` from ``W - delta`` down to ``delta + 1`` (the *region*), and for each copies
    the current value of ``(h + dy, w + dx)`` into ``(h, w)`` (the 'swap' of two views is a one-way
    copy). The value copied is final if the source was visited earlier (it is in the region and
    later in raster order), else it is still the original. So the final value of ``p`` is the
    original value at ``src(q)``, where ``q`` follows ``p -> src(p) -> ...`` while the source was
    visited earlier; the chain strictly increases in raster order, so it is found by pointer
    jumping in ``O(log(chain length))`` batched gathers instead of ``H * W`` sequential steps.

    ``offsets`` ``(B, 2, H, W)`` int64: ``(dy, dx)`` drawn for each pixel (used in the region only).
    Returns ``(B, H * W)`` int64 flat indices into the original image.
    """
    b = offsets.shape[0]
    device = offsets.device
    hh = torch.arange(height, device=device).view(1, height, 1)
    ww = torch.arange(width, device=device).view(1, 1, width)
    lo, hi_h, hi_w = delta + 1, height - delta, width - delta

    def in_region(r: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return (r >= lo) & (r <= hi_h) & (c >= lo) & (c <= hi_w)

    region = in_region(hh, ww).expand(b, height, width)
    sr = (hh + offsets[:, 0]).clamp(0, height - 1)
    sc = (ww + offsets[:, 1]).clamp(0, width - 1)
    sr = torch.where(region, sr, hh.expand_as(sr))
    sc = torch.where(region, sc, ww.expand_as(sc))
    src = (sr * width + sc).reshape(b, -1)
    own = (hh * width + ww).reshape(1, -1).expand(b, -1)
    # the source was visited before p: in the region and later in raster (= scan) order
    earlier = (in_region(sr, sc).reshape(b, -1) & (src > own)) & region.reshape(b, -1)
    jump = torch.where(earlier, src, own)  # fixpoint where the chain stops
    while True:
        nxt = jump.gather(1, jump)
        if torch.equal(nxt, jump):
            break
        jump = nxt
    return src.gather(1, jump)


def glass_blur(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Blur, quantise to uint8, locally shuffle pixels (``iterations`` passes), blur again."""
    sigma, delta, iterations = GLASS_BLUR[severity - 1]
    b, c, h, w = x.shape
    # the reference's np.uint8(blur * 255): truncate (the tiny offset absorbs float32 rounding)
    y = torch.floor(_gaussian_blur(x, sigma) * 255.0 + 1e-3).clamp_(0, 255) / 255.0
    flat = y.reshape(b, c, h * w)
    for _ in range(iterations):
        offsets = torch.randint(-delta, delta, (b, 2, h, w), generator=g, device=x.device)
        srcs = glass_shuffle_sources(offsets, h, w, delta)
        flat = flat.gather(2, srcs[:, None, :].expand(b, c, h * w))
    return _gaussian_blur(flat.reshape(b, c, h, w), sigma)


def gaussian_blur(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Gaussian blur with sigma 1, 2, 3, 4, 6 pixels (edges replicated); no randomness."""
    return _gaussian_blur(x, GAUSSIAN_BLUR[severity - 1])
