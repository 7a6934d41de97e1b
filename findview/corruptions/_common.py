"""Shared helpers of the corruption operations: random generators, Gaussian blur, shifts.

Internal convention: every operation takes ``x``, a ``(B, 3, H, W)`` float32 tensor with values in
[0, 1], and a ``torch.Generator`` on ``x.device``, and returns a float tensor of the same shape whose
values, times 255, are what the reference computes before its final conversion to uint8.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
import torch.nn.functional as F


def device_generator(generator: torch.Generator | None, device: torch.device) -> torch.Generator:
    """Return a generator that can drive random ops on ``device``.

    ``None`` gives a fresh generator seeded with 0 (so the output is the same on every call and the
    global RNG is never touched). A generator already on ``device`` is used as is. A generator on
    another device (typically a CPU generator with CUDA images) draws one 63-bit seed that seeds a
    fresh generator on ``device``; the output is then deterministic in the passed generator's state,
    but differs from the CPU output for the same seed (different RNG streams).
    """
    device = torch.device(device)
    if generator is None:
        g = torch.Generator(device=device)
        g.manual_seed(0)
        return g
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator must be a torch.Generator or None, got {type(generator).__name__}")
    if generator.device.type == device.type and (
        device.type == "cpu" or generator.device.index == (device.index if device.index is not None else 0)
    ):
        return generator
    seed = int(torch.randint(0, 2**63 - 1, (1,), generator=generator, device=generator.device).item())
    g = torch.Generator(device=device)
    g.manual_seed(seed)
    return g


def uniform(shape: tuple[int, ...], low: float, high: float, g: torch.Generator, device: torch.device) -> torch.Tensor:
    """Float32 samples uniform in [low, high) of ``shape`` on ``device``."""
    return torch.rand(shape, generator=g, device=device) * (high - low) + low


def gaussian_kernel1d(sigma: float, radius: int) -> np.ndarray:
    """Normalised sampled Gaussian of length ``2 * radius + 1`` (float64), as scipy/skimage/OpenCV use."""
    t = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (t / sigma) ** 2)
    return k / k.sum()


def skimage_radius(sigma: float, truncate: float = 4.0) -> int:
    """Kernel radius (pixels) of ``skimage.filters.gaussian`` / ``scipy.ndimage.gaussian_filter``."""
    return int(truncate * float(sigma) + 0.5)


@lru_cache(maxsize=64)
def _axis_matrix(n: int, sigma: float, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """``(n, n)`` matrix of a 1-D Gaussian blur along an axis of ``n`` pixels, edges replicated.

    Row ``i`` holds the weights of output pixel ``i``: tap ``j - r`` of the kernel lands on input
    pixel ``clamp(i + j - r, 0, n - 1)`` (the replicated border folded into the matrix).
    """
    r = skimage_radius(sigma)
    k = gaussian_kernel1d(sigma, r)
    m = np.zeros((n, n), dtype=np.float64)
    rows = np.arange(n)
    for j in range(2 * r + 1):
        np.add.at(m, (rows, np.clip(rows + j - r, 0, n - 1)), k[j])
    return torch.as_tensor(m, dtype=dtype, device=device)


def gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of ``x`` ``(B, C, H, W)`` with standard deviation ``sigma`` pixels.

    Edge pixels are replicated (scipy's ``mode='nearest'``) and the kernel is cut at 4 sigma,
    matching ``skimage.filters.gaussian(..., sigma)`` applied per channel. Computed as two matrix
    products ``Mh @ x @ Mw^T`` (fast on CPU and GPU for image sides up to a few hundred pixels).
    """
    if skimage_radius(sigma) == 0:
        return x
    _, _, h, w = x.shape
    mh = _axis_matrix(h, float(sigma), x.device, x.dtype)
    mw = _axis_matrix(w, float(sigma), x.device, x.dtype)
    return torch.matmul(torch.matmul(mh, x), mw.T)


def motion_shifts(
    width: int, angle_deg: torch.Tensor, height: int, img_width: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Integer shifts of the reference's motion blur.

    For tap ``i`` in ``range(width)`` and angle ``a`` (degrees, one per image ``(B,)``), the tap is the
    image shifted by ``dy = -ceil(i sin a - 0.5)`` rows and ``dx = -ceil(i cos a - 0.5)`` columns.
    Returns ``dy, dx`` ``(B, width)`` int64 and ``active`` ``(B, width)`` bool: the reference stops
    adding taps (without renormalising) at the first one whose shift reaches the image size.
    """
    a = torch.deg2rad(angle_deg.double())
    i = torch.arange(width, dtype=torch.float64, device=angle_deg.device)
    dy = -torch.ceil(i[None, :] * torch.sin(a)[:, None] - 0.5)
    dx = -torch.ceil(i[None, :] * torch.cos(a)[:, None] - 0.5)
    dy, dx = dy.long(), dx.long()
    inside = (dy.abs() < height) & (dx.abs() < img_width)
    active = torch.cumprod(inside.long(), dim=1).bool()
    return dy, dx, active


def motion_blur_kernel(width: int, sigma: float) -> np.ndarray:
    """One-sided Gaussian tap weights ``exp(-i^2 / (2 sigma^2))`` for ``i`` in ``range(width)``, normalised."""
    i = np.arange(width, dtype=np.float64)
    k = np.exp(-(i**2) / (2.0 * sigma**2))
    return k / k.sum()


def motion_blur(x: torch.Tensor, radius: int, sigma: float, angle_deg: torch.Tensor) -> torch.Tensor:
    """The reference's motion blur: a Gaussian-weighted sum of ``2 * radius + 1`` shifted copies.

    ``x`` ``(B, C, H, W)`` float, ``angle_deg`` ``(B,)`` (one direction per image, degrees). Copy
    ``i`` is ``x`` shifted by ``i`` pixels (rounded per axis) along the direction, with the edge
    pixels replicated; the weights are a one-sided Gaussian of standard deviation ``sigma`` taps.
    """
    b, c, h, w = x.shape
    width = 2 * radius + 1
    weights = torch.as_tensor(motion_blur_kernel(width, sigma), dtype=x.dtype, device=x.device)
    dy, dx, active = motion_shifts(width, angle_deg.to(x.device), h, w)
    wts = weights[None, :] * active.to(x.dtype)  # (B, width)
    # pad by the largest shift of an active tap (inactive taps have weight 0 and are skipped)
    p = int(torch.where(active, torch.maximum(dy.abs(), dx.abs()), torch.zeros_like(dy)).max().item())
    p = max(p, 1)
    xp = F.pad(x, (p, p, p, p), mode="replicate")
    # shifted[y, x] = img[clamp(y - dy), clamp(x - dx)] = xp[y - dy + p, x - dx + p]
    ys = (p - dy).clamp(0, 2 * p).tolist()
    xs = (p - dx).clamp(0, 2 * p).tolist()
    wl = wts.tolist()
    out = torch.zeros_like(x)
    # one strided view (no copy) and one in-place add per image and tap: on CPU this is ~10x faster
    # than a batched gather of the shifted copies (but many small ops: see benchmarks/RESULTS.md)
    for bi in range(b):
        ob = out[bi]
        xb = xp[bi]
        for i in range(width):
            if wl[bi][i] == 0.0:
                continue
            y0, x0 = ys[bi][i], xs[bi][i]
            ob.add_(xb[:, y0 : y0 + h, x0 : x0 + w], alpha=wl[bi][i])
    return out


def clipped_zoom(x: torch.Tensor, zoom: float) -> torch.Tensor:
    """Zoom into the centre of ``x`` ``(B, C, H, W)`` by ``zoom`` (> 1), bilinear, corners aligned.

    Crops the central ``ceil(H / zoom) x ceil(W / zoom)`` block and resizes it to
    ``round(ceil(H / zoom) * zoom)`` (same for W), like ``scipy.ndimage.zoom(order=1)``; the result may
    be a few pixels larger than ``H x W`` (the reference crops later).
    """
    _, _, h, w = x.shape
    ch, cw = int(math.ceil(h / zoom)), int(math.ceil(w / zoom))
    top, left = (h - ch) // 2, (w - cw) // 2
    crop = x[:, :, top : top + ch, left : left + cw]
    oh, ow = int(round(ch * zoom)), int(round(cw * zoom))
    return F.interpolate(crop, size=(oh, ow), mode="bilinear", align_corners=True)


def rgb_to_gray(x: torch.Tensor) -> torch.Tensor:
    """ITU-R 601 luma ``0.299 R + 0.587 G + 0.114 B`` of ``(B, 3, H, W)`` -> ``(B, 1, H, W)``."""
    return 0.299 * x[:, 0:1] + 0.587 * x[:, 1:2] + 0.114 * x[:, 2:3]
