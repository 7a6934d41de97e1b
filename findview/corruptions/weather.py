"""Weather corruptions: snow, spatter, fog (plasma fractal) and frost (texture overlay)."""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch

from ._common import clipped_zoom, gaussian_blur, motion_blur, rgb_to_gray, uniform

# (mean, std of the flake noise, zoom, threshold, motion radius (taps), motion sigma (taps), image weight)
SNOW = (
    (0.1, 0.3, 3, 0.5, 10, 4, 0.8),
    (0.2, 0.3, 2, 0.5, 12, 4, 0.7),
    (0.55, 0.3, 4, 0.9, 12, 8, 0.7),
    (0.55, 0.3, 4.5, 0.85, 12, 8, 0.65),
    (0.55, 0.3, 2.5, 0.85, 12, 12, 0.55),
)
# (mean, std of the liquid noise, blur sigma (pixels), threshold, intensity or mud blur sigma, mud?)
SPATTER = (
    (0.65, 0.3, 4, 0.69, 0.6, 0),
    (0.65, 0.3, 3, 0.68, 0.6, 0),
    (0.65, 0.3, 2, 0.68, 0.5, 0),
    (0.65, 0.3, 1, 0.65, 1.5, 1),
    (0.67, 0.4, 1, 0.65, 1.5, 1),
)
# (fog strength, plasma fractal roughness decay)
FOG = ((1.5, 2.0), (2.0, 2.0), (2.5, 1.7), (2.5, 1.5), (3.0, 1.4))
# (image weight, frost weight)
FROST = ((1.0, 0.4), (0.8, 0.6), (0.7, 0.7), (0.65, 0.7), (0.6, 0.75))

FROST_DIR = Path(__file__).resolve().parent / "frost"
FROST_FILES = ("frost1.png", "frost2.png", "frost3.png", "frost4.jpg", "frost5.jpg")

WATER_RGB = (175 / 255.0, 238 / 255.0, 238 / 255.0)  # pale turquoise
MUD_RGB = (63 / 255.0, 42 / 255.0, 20 / 255.0)  # mud brown


# ----------------------------------------------------------------------------------------- snow
def snow(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Zoomed, thresholded Gaussian flakes, motion-blurred downwards, added twice (and rotated 180
    degrees) to a greyed, brightened image."""
    mean, std, zoom, thr, radius, sigma, weight = SNOW[severity - 1]
    b, _, h, w = x.shape
    layer = mean + std * torch.randn((b, 1, h, w), generator=g, device=x.device, dtype=x.dtype)
    layer = clipped_zoom(layer, zoom)
    layer = torch.where(layer < thr, torch.zeros_like(layer), layer).clamp_(0.0, 1.0)
    angle = uniform((b,), -135.0, -45.0, g, x.device)
    layer = motion_blur(layer, radius, sigma, angle)
    layer = torch.round(layer * 255.0)[:, :, :h, :w] / 255.0
    bright = torch.maximum(x, rgb_to_gray(x) * 1.5 + 0.5)
    x = weight * x + (1.0 - weight) * bright
    return x + layer + torch.flip(layer, dims=(2, 3))


# -------------------------------------------------------------------------------------- spatter
def _water_mask(liquid: np.ndarray) -> np.ndarray:
    """The reference's water-drop intensity for one image: ``liquid`` (H, W) uint8 -> (H, W) float32.

    Edges of the liquid layer (Canny), distance to them (5x5 mask L2 distance transform) capped at
    20 pixels, smoothed, histogram-equalised, embossed and smoothed again, times the liquid layer.
    """
    dist = 255 - cv2.Canny(liquid, 50, 150)
    dist = cv2.distanceTransform(dist, cv2.DIST_L2, 5)
    _, dist = cv2.threshold(dist, 20, 20, cv2.THRESH_TRUNC)
    dist = cv2.blur(dist, (3, 3)).astype(np.uint8)
    dist = cv2.equalizeHist(dist)
    emboss = np.array([[-2, -1, 0], [-1, 1, 1], [0, 1, 2]], dtype=np.float32)
    dist = cv2.filter2D(dist, cv2.CV_8U, emboss)
    dist = cv2.blur(dist, (3, 3)).astype(np.float32)
    return liquid.astype(np.float32) * dist


def spatter(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Severities 1-3: pale turquoise water drops; 4-5: opaque mud blobs.

    The water-drop shading (edge detection and a distance transform) runs per image on the CPU
    with OpenCV; everything else is batched on ``x.device``.
    """
    mean, std, sigma, thr, c4, mud = SPATTER[severity - 1]
    b, _, h, w = x.shape
    liquid = mean + std * torch.randn((b, 1, h, w), generator=g, device=x.device, dtype=x.dtype)
    liquid = gaussian_blur(liquid, sigma)
    liquid = torch.where(liquid < thr, torch.zeros_like(liquid), liquid)
    if not mud:
        lq = torch.floor(liquid * 255.0).clamp_(0, 255).to(torch.uint8)[:, 0].cpu().numpy()
        m = torch.from_numpy(np.stack([_water_mask(lq[i]) for i in range(b)])).to(x.device, x.dtype)[:, None]
        peak = m.amax(dim=(2, 3), keepdim=True)
        m = torch.where(peak > 0, m / peak.clamp(min=1e-12), torch.zeros_like(m)) * c4
        colour = torch.tensor(WATER_RGB, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
        return x + m * colour
    m = (liquid > thr).to(x.dtype)
    m = gaussian_blur(m, c4)
    m = torch.where(m < 0.8, torch.zeros_like(m), m)
    colour = torch.tensor(MUD_RGB, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return x * (1.0 - m) + colour * m


# ------------------------------------------------------------------------------------------ fog
def plasma_fractal(batch: int, mapsize: int, decay: float, g: torch.Generator, device: torch.device) -> torch.Tensor:
    """Diamond-square height maps ``(batch, mapsize, mapsize)`` in [0, 1] (``mapsize`` a power of 2).

    Starting from 0 at the corner, each level sets the square centres and then the diamond centres
    to the mean of their four neighbours (wrapping around) plus uniform noise in
    ``[-wibble^2, wibble^2)``, with ``wibble = 100`` divided by ``decay`` at each level.
    """
    m = torch.zeros((batch, mapsize, mapsize), device=device)
    step = mapsize
    wibble = 100.0

    def wibbled_mean(a: torch.Tensor) -> torch.Tensor:
        return a / 4 + wibble * uniform(tuple(a.shape), -wibble, wibble, g, device)

    while step >= 2:
        half = step // 2
        corners = m[:, 0::step, 0::step]
        acc = corners + torch.roll(corners, -1, dims=1)
        acc = acc + torch.roll(acc, -1, dims=2)
        m[:, half::step, half::step] = wibbled_mean(acc)
        centres = m[:, half::step, half::step]
        corners = m[:, 0::step, 0::step]
        lt = centres + torch.roll(centres, 1, dims=1) + corners + torch.roll(corners, -1, dims=2)
        m[:, 0::step, half::step] = wibbled_mean(lt)
        tt = centres + torch.roll(centres, 1, dims=2) + corners + torch.roll(corners, -1, dims=1)
        m[:, half::step, 0::step] = wibbled_mean(tt)
        step //= 2
        wibble /= decay
    m = m - m.amin(dim=(1, 2), keepdim=True)
    return m / m.amax(dim=(1, 2), keepdim=True)


def fog(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """Add ``strength`` times a plasma fractal, then rescale by ``max / (max + strength)``."""
    strength, decay = FOG[severity - 1]
    b, _, h, w = x.shape
    size = 1 << max(0, (max(h, w, 3) - 1).bit_length())
    plasma = plasma_fractal(b, size, decay, g, x.device)[:, None, :h, :w].to(x.dtype)
    peak = x.amax(dim=(1, 2, 3), keepdim=True)
    return (x + strength * plasma) * peak / (peak + strength)


# ---------------------------------------------------------------------------------------- frost
def frost_texture_paths() -> tuple[Path, ...]:
    """Paths of the five frost textures shipped with the package."""
    return tuple(FROST_DIR / name for name in FROST_FILES)


def missing_frost_textures() -> list[Path]:
    """The frost texture files that are absent (empty when all five are present)."""
    return [p for p in frost_texture_paths() if not p.is_file()]


def frost_textures_available() -> bool:
    """True when all five frost textures are present next to this module."""
    return not missing_frost_textures()


def check_frost_textures() -> None:
    """Raise a one-line ``FileNotFoundError`` naming the first missing frost texture and how to get it."""
    missing = missing_frost_textures()
    if missing:
        raise FileNotFoundError(
            f"frost texture {missing[0]} not found ({len(missing)} of {len(FROST_FILES)} missing): reinstall "
            f"findview with its package data (pip install .) or copy {', '.join(FROST_FILES)} from the "
            f"imagecorruptions 1.1.2 package (Apache-2.0) into {FROST_DIR}"
        )


@lru_cache(maxsize=32)
def _frost_rescaled(index: int, height: int, width: int) -> np.ndarray:
    """Texture ``index`` (RGB uint8) resized (bicubic) to cover ``height x width`` with a 10% margin.

    As the reference: scale 1 if the texture already covers the image, else the factor that makes
    the short side fit (the larger one if both are short); then 1.1 times that, sizes rounded up.
    """
    check_frost_textures()
    path = frost_texture_paths()[index]
    tex = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if tex is None:
        raise FileNotFoundError(f"frost texture {path} cannot be decoded: reinstall findview (pip install .)")
    th, tw = tex.shape[:2]
    if th >= height and tw >= width:
        scale = 1.0
    elif th < height and tw >= width:
        scale = height / th
    elif th >= height and tw < width:
        scale = width / tw
    else:
        scale = max(height / th, width / tw)
    scale *= 1.1
    size = (int(math.ceil(tw * scale)), int(math.ceil(th * scale)))
    tex = cv2.resize(tex, dsize=size, interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(tex[..., ::-1])


def frost(x: torch.Tensor, severity: int, g: torch.Generator) -> torch.Tensor:
    """``a * x + b * frost`` with one of five textures per image, cropped at a random position."""
    b = x.shape[0]
    textures = torch.randint(0, len(FROST_FILES), (b,), generator=g, device=x.device)
    positions = torch.rand((b, 2), generator=g, device=x.device, dtype=torch.float64)
    return frost_blend(x, severity, textures, positions)


def frost_blend(x: torch.Tensor, severity: int, textures: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """Frost with given draws: ``textures`` ``(B,)`` in 0-4 (frost1-frost5) and ``positions``
    ``(B, 2)`` in [0, 1), the crop's top and left offsets as fractions of the free range (the
    reference's ``randint(0, Ht - H)``, ``randint(0, Wt - W)``)."""
    a, f = FROST[severity - 1]
    b, _, h, w = x.shape
    idx = textures.tolist()
    u = positions.double().cpu().tolist()
    layer = torch.empty_like(x)
    for i in range(b):  # one strided copy per image
        tex = _frost_tensor(int(idx[i]), h, w, x.device)
        th, tw = tex.shape[1:]
        # offsets uniform in [0, Ht - h) x [0, Wt - w), like randint
        top = min(int(u[i][0] * (th - h)), th - h - 1)
        left = min(int(u[i][1] * (tw - w)), tw - w - 1)
        layer[i] = tex[:, top : top + h, left : left + w]
    return layer.mul_(f).add_(x, alpha=a)


@lru_cache(maxsize=32)
def _frost_tensor(index: int, height: int, width: int, device: torch.device) -> torch.Tensor:
    """:func:`_frost_rescaled` as a float32 ``(3, Ht, Wt)`` tensor in [0, 1] on ``device`` (cached)."""
    tex = torch.from_numpy(_frost_rescaled(index, height, width).copy())
    return tex.permute(2, 0, 1).to(device=device, dtype=torch.float32).div_(255.0).contiguous()
