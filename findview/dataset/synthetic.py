"""Procedural equirectangular panoramas: findview's built-in data set (no download needed).

Each panorama is ray-cast: every panorama pixel's direction (the SPEC section 1 mapping: ``lon`` right
of the image centre, ``lat`` up) is intersected with a small 3D scene around a camera at the origin, and
the hit surface's texture is sampled at the hit point (metres -> texels, bilinear, 3-level mip-mapping
against aliasing). Views rendered from the panorama are therefore perspective-consistent.

Scene kinds (the labels of the default data set):

- ``room``: a box room (walls, floor, ceiling) with 3-6 pieces of furniture (boxes);
- ``hall``: a larger room with 6-12 pieces of furniture (shelves, tables, crates);
- ``landscape``: an infinite ground plane, scattered rocks and walls, 3 layers of mountains on the
  horizon, a sky gradient with a sun and a cloud layer (a textured plane 1.5 km up);
- ``village``: the landscape with buildings (windows, doors, signs) and crates.

Textures are painted per surface in metric units with OpenCV: multi-octave value noise (random lattice
values, cubic-interpolated) mixed with per-scene random palettes, sharp-edged blotches, and many random
objects (posters, bookshelves, pixel-art "photos", random text, planks, tiles, stones, windows), so that
no two directions look alike and ORB finds hundreds of keypoints in most perspective views. Everything
derives from ``numpy.random.default_rng(seed)``: the same seed gives the same image on the same
library versions.

:func:`ensure_synthetic_images` writes the data set under ``<root>/<label>/synth_XXXX.jpg`` (JPEG
quality 95) with a manifest ``<root>/synthetic.json``, regenerating only when the parameters change.
"""

from __future__ import annotations

import colorsys
import math
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from findview.dataset.discovery import DatasetError, ImageEntry
from findview.utils import atomic_write, read_json, write_json

__all__ = [
    "GENERATOR_VERSION",
    "SCENE_KINDS",
    "MANIFEST",
    "generate_panorama",
    "synthetic_image_seed",
    "ensure_synthetic_images",
]

GENERATOR_VERSION = 1
SCENE_KINDS = ("room", "hall", "landscape", "village")
MANIFEST = "synthetic.json"

_F32 = np.float32
_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
)
_CHARS = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz0123456789 #&+-%@"))
_MIP_LEVELS = 3


# ----------------------------------------------------------------------------------------------------
# noise and colours
# ----------------------------------------------------------------------------------------------------
def _noise(rng: np.random.Generator, h: int, w: int, cell: float, wrap: bool = False) -> np.ndarray:
    """Smooth value noise ``(h, w)`` float32 (lattice spacing ``cell`` texels, unit-variance lattice).

    With ``wrap`` the result tiles seamlessly when ``h`` and ``w`` are multiples of ``cell`` (otherwise
    it silently does not wrap).
    """
    cell = max(1, int(round(cell)))
    if cell == 1:
        return rng.standard_normal((h, w), dtype=_F32)
    if wrap and h % cell == 0 and w % cell == 0:
        gh, gw = h // cell, w // cell
        g = np.pad(rng.standard_normal((gh, gw), dtype=_F32), 2, mode="wrap")
        big = cv2.resize(g, ((gw + 4) * cell, (gh + 4) * cell), interpolation=cv2.INTER_CUBIC)
        return np.ascontiguousarray(big[2 * cell : 2 * cell + h, 2 * cell : 2 * cell + w])
    gh, gw = h // cell + 4, w // cell + 4
    g = rng.standard_normal((gh, gw), dtype=_F32)
    big = cv2.resize(g, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)
    oy, ox = (int(v) for v in rng.integers(cell, 2 * cell, size=2))
    return np.ascontiguousarray(big[oy : oy + h, ox : ox + w])


def _fbm(
    rng: np.random.Generator, h: int, w: int, cell: float, octaves: int = 4, gain: float = 0.55, wrap: bool = False
) -> np.ndarray:
    """Multi-octave value noise, standardised to mean 0 / std 1, ``(h, w)`` float32.

    Octaves with a lattice spacing of 16 texels or more are summed at 1/4 resolution and upsampled
    once (they are smooth), the finer ones are made at full resolution.
    """
    octs = []
    amp = 1.0
    for _ in range(octaves):
        if cell < 1:
            break
        octs.append((cell, amp))
        amp *= gain
        cell /= 2
    can_wrap = h % 4 == 0 and w % 4 == 0
    low = [(c, a) for c, a in octs if c >= 16 and (not wrap or (can_wrap and int(round(c)) % 4 == 0))]
    out = np.zeros((h, w), _F32)
    if low:
        if wrap:
            hl, wl = h // 4, w // 4
            acc = sum(a * _noise(rng, hl, wl, c / 4, True) for c, a in low)
            acc = np.pad(acc, 1, mode="wrap")
            out += cv2.resize(acc, ((wl + 2) * 4, (hl + 2) * 4), interpolation=cv2.INTER_LINEAR)[4 : 4 + h, 4 : 4 + w]
        else:
            hl, wl = h // 4 + 2, w // 4 + 2
            acc = sum(a * _noise(rng, hl, wl, c / 4, False) for c, a in low)
            out += cv2.resize(acc, (wl * 4, hl * 4), interpolation=cv2.INTER_LINEAR)[:h, :w]
    for c, a in octs:
        if (c, a) not in low:
            out += a * _noise(rng, h, w, c, wrap)
    out -= out.mean()
    out /= out.std() + 1e-6
    return out


def _rgb(rng: np.random.Generator, s: tuple[float, float] = (0.2, 0.8), v: tuple[float, float] = (0.3, 0.9),
         hue: float | None = None, hue_jitter: float = 1.0) -> tuple[int, int, int]:
    """A random colour (RGB ints 0..255) from HSV ranges; ``hue`` in [0, 1) with ``hue_jitter`` spread."""
    hh = rng.random() if hue is None else (hue + rng.uniform(-hue_jitter, hue_jitter)) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hh, rng.uniform(*s), rng.uniform(*v))
    return int(r * 255), int(g * 255), int(b * 255)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``a + (b - a) * t`` (float32, broadcasting), with few temporaries."""
    out = np.subtract(b, a, dtype=_F32)
    if out.shape != np.broadcast_shapes(np.shape(a), np.shape(b), np.shape(t)):
        out = out * t
    else:
        out *= t
    out += a
    return out


def _material(
    rng: np.random.Generator,
    h: int,
    w: int,
    ppm: float,
    colors: Sequence[tuple[int, int, int]],
    scale_m: float = 0.6,
    blotch: float = 0.5,
    grain: float = 10.0,
) -> np.ndarray:
    """A base material ``(h, w, 3)`` uint8: two-colour fbm, sharp-edged blotches of a third colour,
    fine grain. ``scale_m`` is the largest noise feature in metres, ``ppm`` texels per metre."""
    c = [np.array(cc, _F32) for cc in colors]
    n1 = _fbm(rng, h, w, max(2.0, scale_m * ppm), 5)
    img = _mix(c[0], c[1], np.clip(0.5 + 0.3 * n1, 0, 1)[..., None])
    if blotch > 0 and len(c) > 2:
        n2 = _fbm(rng, h, w, max(2.0, 0.5 * scale_m * ppm), 4)
        thr = 1.4 - 1.6 * blotch
        m = np.clip((n2 - thr) * 6.0, 0, 1)[..., None]
        img = _mix(img, c[2], 0.85 * m)
    if grain > 0:
        img += grain * _noise(rng, h, w, rng.choice([1, 2]))[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------
# drawing helpers (texel units; images are RGB uint8)
# ----------------------------------------------------------------------------------------------------
def _ip(*v: float) -> tuple[int, ...]:
    return tuple(int(round(x)) for x in v)


def _contrast(c: tuple[int, int, int], rng: np.random.Generator) -> tuple[int, int, int]:
    lum = 0.3 * c[0] + 0.59 * c[1] + 0.11 * c[2]
    return _rgb(rng, (0, 0.6), (0.0, 0.25)) if lum > 120 else _rgb(rng, (0, 0.4), (0.8, 1.0))


def _text(img: np.ndarray, rng: np.random.Generator, x: float, y: float, height: float,
          color: tuple[int, int, int], max_width: float | None = None) -> None:
    """Random text, baseline at ``(x, y)``, capital height about ``height`` texels."""
    if height < 4:
        return
    s = "".join(rng.choice(_CHARS, size=int(rng.integers(3, 14)))).strip() or "X"
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    (_, h1), _ = cv2.getTextSize("H", font, 1.0, 1)
    scale = height / max(h1, 1)
    thick = max(1, int(round(height / rng.uniform(7, 14))))
    if max_width is not None:
        while len(s) > 1 and cv2.getTextSize(s, font, scale, thick)[0][0] > max_width:
            s = s[:-1]
    cv2.putText(img, s, _ip(x, y), font, scale, color, thick, cv2.LINE_AA)


def _pixel_art(img: np.ndarray, rng: np.random.Generator, x0: int, y0: int, w: int, h: int) -> None:
    """A blocky random 'photo' (random palette, random block size) in the rectangle."""
    H, W = img.shape[:2]
    x0, y0 = max(0, x0), max(0, y0)
    w, h = min(w, W - x0), min(h, H - y0)
    if w < 4 or h < 4:
        return
    block = int(rng.integers(2, 8))
    gh, gw = max(1, h // block), max(1, w // block)
    k = int(rng.integers(3, 7))
    pal = np.array([_rgb(rng, (0.1, 1), (0.1, 1)) for _ in range(k)], np.uint8)
    smooth = _noise(rng, gh, gw, max(1.0, min(gh, gw) / rng.uniform(1.5, 4)))
    idx = np.clip(((smooth - smooth.min()) / (np.ptp(smooth) + 1e-6) * k).astype(int), 0, k - 1)
    flip = rng.random((gh, gw)) < 0.25
    idx[flip] = rng.integers(0, k, size=int(flip.sum()))
    img[y0 : y0 + h, x0 : x0 + w] = cv2.resize(pal[idx], (w, h), interpolation=cv2.INTER_NEAREST)


def _poster(img: np.ndarray, rng: np.random.Generator, x0: float, y0: float, w: float, h: float) -> None:
    """A rectangle with random content: text lines, pixel-art photo, circles, polygons."""
    x0, y0, w, h = _ip(x0, y0, w, h)
    if w < 6 or h < 6:
        return
    bg = _rgb(rng, (0.0, 0.9), (0.25, 1.0))
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), bg, -1)
    fg = _contrast(bg, rng)
    for _ in range(int(rng.integers(2, 9))):
        kind = rng.random()
        cx, cy = x0 + rng.uniform(0.05, 0.8) * w, y0 + rng.uniform(0.1, 0.9) * h
        if kind < 0.35:
            _text(img, rng, cx, cy, rng.uniform(0.06, 0.2) * h, fg if rng.random() < 0.6 else _rgb(rng), x0 + w - cx)
        elif kind < 0.55:
            pw, ph = rng.uniform(0.2, 0.6) * w, rng.uniform(0.2, 0.6) * h
            _pixel_art(img, rng, *_ip(cx - pw / 2, cy - ph / 2, pw, ph))
        elif kind < 0.75:
            r = rng.uniform(0.04, 0.2) * min(w, h)
            cv2.circle(img, _ip(cx, cy), int(r), _rgb(rng), -1 if rng.random() < 0.6 else 2, cv2.LINE_AA)
        else:
            pts = np.stack([cx + rng.uniform(-0.2, 0.2, 5) * w, cy + rng.uniform(-0.2, 0.2, 5) * h], 1)
            cv2.fillPoly(img, [pts.astype(np.int32)], _rgb(rng), cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), _rgb(rng, (0, 0.4), (0.05, 0.5)), int(rng.integers(1, 4)))


def _bookshelf(img: np.ndarray, rng: np.random.Generator, x0: float, y0: float, w: float, h: float, ppm: float) -> None:
    """Shelves of books with random widths, heights and colours."""
    x0, y0, w, h = _ip(x0, y0, w, h)
    board = _rgb(rng, (0.2, 0.6), (0.2, 0.6))
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), tuple(int(c * 0.4) for c in board), -1)
    rows = max(1, int(h / (rng.uniform(0.3, 0.45) * ppm)))
    rh = h / rows
    for r in range(rows):
        ybot = y0 + (r + 1) * rh
        x = x0 + 2.0
        while x < x0 + w - 3:
            bw = rng.uniform(0.015, 0.06) * ppm + 1
            if rng.random() < 0.08:
                x += bw * 3  # a gap
                continue
            bh = rh * rng.uniform(0.55, 0.92)
            col = _rgb(rng, (0.2, 0.9), (0.15, 0.95))
            cv2.rectangle(img, _ip(x, ybot - bh), _ip(min(x + bw, x0 + w - 2), ybot - 2), col, -1)
            if bw > 5 and rng.random() < 0.5:
                cv2.line(img, _ip(x + 1, ybot - bh * rng.uniform(0.3, 0.8)), _ip(x + bw - 1, ybot - bh * rng.uniform(0.3, 0.8)),
                         _contrast(col, rng), 1)
            x += bw + rng.uniform(0, 1.5)
        cv2.rectangle(img, _ip(x0, ybot - 2), _ip(x0 + w, ybot + 1), board, -1)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), board, 3)


def _rgb_batch(rng: np.random.Generator, n: int, s: tuple[float, float] = (0.2, 0.8), v: tuple[float, float] = (0.3, 0.9),
               hue: float | None = None, hue_jitter: float = 1.0) -> np.ndarray:
    """``n`` random colours ``(n, 3)`` int (RGB 0..255), vectorised :func:`_rgb`."""
    hh = rng.random(n) if hue is None else np.mod(hue + rng.uniform(-hue_jitter, hue_jitter, n), 1.0)
    ss, vv = rng.uniform(*s, n), rng.uniform(*v, n)
    i = np.floor(hh * 6).astype(int) % 6
    f = hh * 6 - np.floor(hh * 6)
    p, q, t = vv * (1 - ss), vv * (1 - ss * f), vv * (1 - ss * (1 - f))
    table = np.stack([np.stack(c, 1) for c in ((vv, t, p), (q, vv, p), (p, vv, t), (p, q, vv), (t, p, vv), (vv, p, q))], 0)
    return (table[i, np.arange(n)] * 255).astype(int)


def _scatter_shapes(img: np.ndarray, rng: np.random.Generator, count: int, size: tuple[float, float],
                    color: tuple = (), outline: float = 0.5) -> None:
    """``count`` random small filled polygons / ellipses (stones, stains, clutter); ``color`` holds the
    HSV ranges of :func:`_rgb` (s, v, hue, hue_jitter)."""
    H, W = img.shape[:2]
    if count <= 0:
        return
    cols = _rgb_batch(rng, count, *color).tolist()
    cx, cy = rng.uniform(0, W, count), rng.uniform(0, H, count)
    lo_r, hi_r = sorted((float(size[0]), float(size[1])))
    rad = rng.uniform(lo_r, hi_r, count)
    poly = rng.random(count) < 0.5
    outl = rng.random(count) < outline
    nv = rng.integers(4, 8, count)
    ang = np.sort(rng.uniform(0, 2 * np.pi, (count, 7)), axis=1)
    rr = rng.uniform(0.5, 1.0, (count, 7))
    squash = rng.uniform(0.4, 1.0, count)
    rot = rng.uniform(0, 180, count)
    px = (cx[:, None] + rad[:, None] * rr * np.cos(ang)).astype(np.int32)
    py = (cy[:, None] + rad[:, None] * rr * np.sin(ang)).astype(np.int32)
    for k in range(count):
        col = tuple(cols[k])
        if poly[k]:
            pts = np.stack([px[k, : nv[k]], py[k, : nv[k]]], 1)
            cv2.fillPoly(img, [pts], col, cv2.LINE_AA)
            if outl[k]:
                cv2.polylines(img, [pts], True, (col[0] * 9 // 20, col[1] * 9 // 20, col[2] * 9 // 20), 1, cv2.LINE_AA)
        else:
            axes = (max(1, int(rad[k])), max(1, int(rad[k] * squash[k])))
            cv2.ellipse(img, (int(cx[k]), int(cy[k])), axes, float(rot[k]), 0, 360, col, -1, cv2.LINE_AA)


def _wrap_draw(img: np.ndarray, draw: Callable[[np.ndarray], None], margin: int) -> None:
    """Draw on a tileable texture without seams: ``draw`` paints on the texture padded (wrap) by
    ``margin`` texels on each side; every changed texel is then folded back to its periodic position."""
    H, W = img.shape[:2]
    m = int(margin)
    canvas = np.pad(img, ((m, m), (m, m), (0, 0)), mode="wrap")
    ref = canvas.copy()
    draw(canvas)
    ys, xs = np.nonzero(np.any(canvas != ref, axis=2))
    img[(ys - m) % H, (xs - m) % W] = canvas[ys, xs]


# ----------------------------------------------------------------------------------------------------
# surface painters
# ----------------------------------------------------------------------------------------------------
class _Style:
    """Per-scene palette."""

    def __init__(self, rng: np.random.Generator, outdoor: bool) -> None:
        self.hue = rng.random()
        self.wall = [_rgb(rng, (0.05, 0.45), (0.55, 0.95), self.hue, 0.08) for _ in range(3)]
        self.floor = [_rgb(rng, (0.3, 0.8), (0.25, 0.75), rng.random(), 0.05) for _ in range(3)]
        self.ceiling = [_rgb(rng, (0.0, 0.15), (0.75, 0.98)) for _ in range(3)]
        self.accent = [_rgb(rng, (0.4, 1.0), (0.4, 1.0)) for _ in range(4)]
        self.outdoor = outdoor


def _paint_wall(rng: np.random.Generator, st: _Style, w: int, h: int, ppm: float, big: bool) -> np.ndarray:
    wall_colors = [st.wall[0], st.wall[1], st.wall[2] if rng.random() < 0.5 else st.accent[int(rng.integers(4))]]
    img = _material(rng, h, w, ppm, wall_colors, scale_m=rng.uniform(0.3, 1.0), blotch=rng.uniform(0.2, 0.6))
    W_m, H_m = w / ppm, h / ppm
    floor_y = h  # texel row of the floor (v = 0 at the ceiling)
    # skirting board
    sk = int(rng.uniform(0.06, 0.14) * ppm)
    cv2.rectangle(img, (0, floor_y - sk), (w, floor_y), _rgb(rng, (0, 0.5), (0.1, 0.8)), -1)
    # windows / doors
    for _ in range(int(rng.integers(0, 3))):
        ww, wh = rng.uniform(0.6, 1.8) * ppm, rng.uniform(0.8, 1.5) * ppm
        x, y = rng.uniform(0, max(1, w - ww)), floor_y - rng.uniform(0.9, 1.1) * ppm - wh
        sky = np.array(_rgb(rng, (0.2, 0.6), (0.7, 1.0), 0.58, 0.05), _F32)
        x0, y0, x1, y1 = _ip(x, y, x + ww, y + wh)
        y0 = max(0, y0)
        if x1 - x0 > 8 and y1 - y0 > 8:
            grad = np.linspace(1.0, 0.75, y1 - y0, dtype=_F32)[:, None, None] * sky
            img[y0:y1, x0:x1] = np.clip(grad, 0, 255).astype(np.uint8)
            _scatter_shapes(img[y0:y1, x0:x1], rng, int(rng.integers(3, 9)), (3, (y1 - y0) / 4),
                            ((0.2, 0.7), (0.2, 0.7),))
            frame = _rgb(rng, (0, 0.2), (0.3, 1.0))
            cv2.rectangle(img, (x0, y0), (x1, y1), frame, max(2, int(0.04 * ppm)))
            cv2.line(img, ((x0 + x1) // 2, y0), ((x0 + x1) // 2, y1), frame, max(1, int(0.02 * ppm)))
    if rng.random() < 0.7:
        dw, dh = rng.uniform(0.8, 1.0) * ppm, rng.uniform(2.0, 2.2) * ppm
        x = rng.uniform(0, max(1, w - dw))
        col = _rgb(rng, (0.1, 0.7), (0.2, 0.8))
        cv2.rectangle(img, _ip(x, floor_y - dh), _ip(x + dw, floor_y), col, -1)
        cv2.rectangle(img, _ip(x, floor_y - dh), _ip(x + dw, floor_y), _contrast(col, rng), max(2, int(0.03 * ppm)))
        cv2.circle(img, _ip(x + 0.85 * dw, floor_y - 1.0 * ppm), max(2, int(0.03 * ppm)), (220, 200, 120), -1)
        if rng.random() < 0.5:
            _poster(img, rng, x + 0.2 * dw, floor_y - 0.8 * dh, 0.6 * dw, 0.2 * dh)
    # bookshelves
    for _ in range(int(rng.integers(0, 3 if big else 2))):
        bw, bh = rng.uniform(0.8, 2.5) * ppm, rng.uniform(1.0, 2.0) * ppm
        x = rng.uniform(0, max(1, w - bw))
        _bookshelf(img, rng, x, floor_y - bh - rng.uniform(0, 0.3) * ppm, bw, bh, ppm)
    # posters, pictures, notes
    n_post = int(rng.poisson(W_m * H_m * rng.uniform(0.5, 1.0))) + 2
    for _ in range(n_post):
        pw, ph = rng.uniform(0.2, 1.0) * ppm, rng.uniform(0.2, 1.0) * ppm
        x, y = rng.uniform(-0.1 * pw, max(-0.1 * pw, w - 0.9 * pw)), floor_y - rng.uniform(0.8, max(1.0, H_m - 0.3)) * ppm - ph / 2
        _poster(img, rng, x, y, pw, ph)
    for _ in range(int(rng.poisson(W_m * H_m * 1.5))):
        x, y = rng.uniform(0, w), rng.uniform(0.1 * h, h - sk)
        _text(img, rng, x, y, rng.uniform(0.03, 0.12) * ppm, _rgb(rng, (0, 1), (0, 0.6)), None)
    # switches / outlets
    for _ in range(int(rng.integers(1, 5))):
        x, y = rng.uniform(0, w), floor_y - rng.choice([0.3, 1.1]) * ppm
        s = 0.08 * ppm
        cv2.rectangle(img, _ip(x, y), _ip(x + s, y + s * 1.4), (235, 235, 230), -1)
        cv2.rectangle(img, _ip(x, y), _ip(x + s, y + s * 1.4), (90, 90, 90), 1)
    return img


def _paint_floor(rng: np.random.Generator, st: _Style, w: int, h: int, ppm: float) -> np.ndarray:
    img = _material(rng, h, w, ppm, st.floor, scale_m=1.0, blotch=0.3, grain=6)
    if rng.random() < 0.55:  # planks: rows of random width, random lengths and tints
        y = 0.0
        while y < h:
            ph = rng.uniform(0.1, 0.25) * ppm
            x = -rng.uniform(0, 1.5) * ppm
            while x < w:
                pl = rng.uniform(0.6, 2.2) * ppm
                tint = np.array(st.floor[int(rng.integers(3))], _F32) * rng.uniform(0.75, 1.2)
                x0, y0, x1, y1 = _ip(max(0, x), y, min(w, x + pl), min(h, y + ph))
                if x1 > x0 and y1 > y0:
                    reg = img[y0:y1, x0:x1].astype(_F32)
                    img[y0:y1, x0:x1] = np.clip(reg * 0.5 + tint * 0.5, 0, 255).astype(np.uint8)
                    cv2.rectangle(img, (x0, y0), (x1, y1), tuple(int(c * 0.35) for c in st.floor[0]), 1)
                x += pl
            y += ph
        grain = _noise(rng, h, max(1, w // 8), 2)
        grain = cv2.resize(grain, (w, h), interpolation=cv2.INTER_LINEAR)
        img = np.clip(img.astype(_F32) + 14 * grain[..., None], 0, 255).astype(np.uint8)
    else:  # tiles with per-tile colours
        ts = rng.uniform(0.3, 0.6) * ppm
        grout = _rgb(rng, (0, 0.2), (0.2, 0.8))
        for ty in range(int(h / ts) + 1):
            for tx in range(int(w / ts) + 1):
                col = np.array(st.floor[int(rng.integers(3))], _F32) * rng.uniform(0.8, 1.15)
                x0, y0, x1, y1 = _ip(tx * ts, ty * ts, (tx + 1) * ts, (ty + 1) * ts)
                reg = img[y0:y1, x0:x1].astype(_F32)
                if reg.size:
                    img[y0:y1, x0:x1] = np.clip(reg * 0.45 + col * 0.55, 0, 255).astype(np.uint8)
                    cv2.rectangle(img, (x0, y0), (x1, y1), grout, max(1, int(0.01 * ppm)))
    # rugs
    for _ in range(int(rng.integers(0, 3))):
        rw, rh = rng.uniform(1.0, 3.0) * ppm, rng.uniform(0.8, 2.0) * ppm
        x, y = rng.uniform(0, max(1, w - rw)), rng.uniform(0, max(1, h - rh))
        x0, y0, x1, y1 = _ip(x, y, x + rw, y + rh)
        col = _rgb(rng, (0.3, 0.9), (0.2, 0.8))
        cv2.rectangle(img, (x0, y0), (x1, y1), col, -1)
        for b in range(int(rng.integers(1, 4))):
            inset = int((b + 1) * rng.uniform(0.04, 0.1) * ppm)
            cv2.rectangle(img, (x0 + inset, y0 + inset), (x1 - inset, y1 - inset), _rgb(rng), max(1, int(0.02 * ppm)))
        _scatter_shapes(img[y0:y1, x0:x1], rng, int(rng.integers(5, 25)), (0.03 * ppm, 0.15 * ppm), ())
    # clutter: papers, stains
    _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 1.5)), (0.02 * ppm, 0.12 * ppm),
                    ((0, 0.8), (0.1, 0.9),))
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.4))):
        _poster(img, rng, rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.15, 0.4) * ppm, rng.uniform(0.15, 0.4) * ppm)
    return img


def _paint_ceiling(rng: np.random.Generator, st: _Style, w: int, h: int, ppm: float) -> np.ndarray:
    img = _material(rng, h, w, ppm, st.ceiling, scale_m=0.8, blotch=0.35, grain=6)
    ps = rng.uniform(0.5, 0.7) * ppm
    line = _rgb(rng, (0, 0.2), (0.3, 0.6))
    y = rng.uniform(0, ps)
    while y < h:  # panels with per-panel shade and jittered seams
        x = rng.uniform(0, ps)
        while x < w:
            pw = ps * rng.uniform(0.8, 1.3)
            x0, y0, x1, y1 = _ip(x, y, x + pw, y + ps)
            reg = img[max(0, y0):y1, max(0, x0):x1]
            if reg.size:
                reg[:] = np.clip(reg.astype(_F32) * rng.uniform(0.82, 1.08), 0, 255).astype(np.uint8)
            cv2.rectangle(img, (x0, y0), (x1, y1), line, 1)
            x += pw
        y += ps
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.25)) + 2):  # lamps
        lx, ly = rng.uniform(0, w), rng.uniform(0, h)
        if rng.random() < 0.5:
            r = rng.uniform(0.1, 0.25) * ppm
            cv2.circle(img, _ip(lx, ly), int(r * 1.3), (90, 90, 90), -1, cv2.LINE_AA)
            cv2.circle(img, _ip(lx, ly), int(r), (255, 250, 225), -1, cv2.LINE_AA)
        else:
            lw, lh = rng.uniform(0.4, 1.2) * ppm, rng.uniform(0.1, 0.3) * ppm
            cv2.rectangle(img, _ip(lx, ly), _ip(lx + lw, ly + lh), (80, 80, 85), -1)
            cv2.rectangle(img, _ip(lx + 3, ly + 3), _ip(lx + lw - 3, ly + lh - 3), (250, 250, 235), -1)
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.3)) + 1):  # vents
        vx, vy = rng.uniform(0, w), rng.uniform(0, h)
        vw, vh = rng.uniform(0.2, 0.5) * ppm, rng.uniform(0.15, 0.4) * ppm
        cv2.rectangle(img, _ip(vx, vy), _ip(vx + vw, vy + vh), (200, 200, 200), -1)
        for k in range(1, int(vh / 4)):
            cv2.line(img, _ip(vx + 2, vy + 4 * k), _ip(vx + vw - 2, vy + 4 * k), (70, 70, 70), 1)
    _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.8)), (0.02 * ppm, 0.1 * ppm),
                    ((0, 0.5), (0.2, 0.9),))
    return img


def _paint_furniture(rng: np.random.Generator, st: _Style, w: int, h: int, ppm: float, top: bool) -> np.ndarray:
    base = [_rgb(rng, (0.2, 0.8), (0.2, 0.85)) for _ in range(2)] + [st.accent[int(rng.integers(4))]]
    img = _material(rng, h, w, ppm, base, scale_m=rng.uniform(0.2, 0.6), blotch=rng.uniform(0.1, 0.5))
    if top:
        for _ in range(int(rng.poisson(w * h / ppm**2 * 6)) + 1):
            pw, ph = rng.uniform(0.1, 0.5) * ppm, rng.uniform(0.1, 0.4) * ppm
            _poster(img, rng, rng.uniform(-pw / 2, w), rng.uniform(-ph / 2, h), pw, ph)
        _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 8)) + 2, (0.03 * ppm, 0.1 * ppm), ())
        return img
    # drawers / doors with handles, random grid
    rows, cols = int(rng.integers(1, 5)), int(rng.integers(1, 4))
    dw, dh = w / cols, h / rows
    edge = _contrast(base[0], rng)
    for r in range(rows):
        for c in range(cols):
            if rng.random() < 0.25:
                continue
            x0, y0 = c * dw + 3, r * dh + 3
            cv2.rectangle(img, _ip(x0, y0), _ip(x0 + dw - 6, y0 + dh - 6), edge, max(1, int(0.01 * ppm)))
            hx, hy = x0 + dw * rng.uniform(0.3, 0.7), y0 + dh * rng.uniform(0.2, 0.5)
            cv2.rectangle(img, _ip(hx - 0.05 * ppm, hy), _ip(hx + 0.05 * ppm, hy + 0.015 * ppm + 2), (60, 60, 60), -1)
    for _ in range(int(rng.integers(0, 4))):
        _poster(img, rng, rng.uniform(0, w * 0.8), rng.uniform(0, h * 0.8), rng.uniform(0.08, 0.3) * ppm, rng.uniform(0.05, 0.2) * ppm)
    return img


def _paint_rock(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    g = rng.uniform(90, 170)
    cols = [_rgb(rng, (0, 0.2), (g / 255 * 0.8, g / 255)), _rgb(rng, (0, 0.25), (0.3, 0.75)), _rgb(rng, (0.3, 0.7), (0.3, 0.6), 0.25, 0.1)]
    img = _material(rng, h, w, ppm, cols, scale_m=rng.uniform(0.3, 1.0), blotch=0.5, grain=14)
    for _ in range(int(rng.integers(3, 12))):  # cracks
        pts = [np.array([rng.uniform(0, w), rng.uniform(0, h)])]
        for _ in range(int(rng.integers(3, 9))):
            pts.append(pts[-1] + rng.normal(0, 0.15 * ppm, 2))
        cv2.polylines(img, [np.array(pts, np.int32)], False, (35, 35, 35), max(1, int(rng.integers(1, 3))), cv2.LINE_AA)
    _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 6)) + 3, (0.02 * ppm, 0.12 * ppm),
                    ((0.2, 0.6), (0.3, 0.8), 0.2, 0.12))
    return img


def _paint_facade(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    cols = [_rgb(rng, (0.05, 0.5), (0.45, 0.95)) for _ in range(2)] + [_rgb(rng, (0.1, 0.6), (0.2, 0.7))]
    img = _material(rng, h, w, ppm, cols, scale_m=rng.uniform(0.5, 2.0), blotch=rng.uniform(0.2, 0.6), grain=12)
    storey = rng.uniform(2.8, 3.6) * ppm
    n_floors = max(1, int(h / storey))
    frame = _rgb(rng, (0, 0.3), (0.1, 0.95))
    for f in range(n_floors):
        ybase = h - f * storey
        x = rng.uniform(0.3, 1.5) * ppm
        while x < w - 0.8 * ppm:
            ww, wh = rng.uniform(0.6, 1.6) * ppm, rng.uniform(0.9, 1.6) * ppm
            y0 = ybase - storey * 0.35 - wh
            if f == 0 and rng.random() < 0.25:  # a door
                dw, dh = rng.uniform(0.9, 1.4) * ppm, rng.uniform(2.0, 2.4) * ppm
                col = _rgb(rng, (0.2, 0.8), (0.15, 0.7))
                cv2.rectangle(img, _ip(x, ybase - dh), _ip(x + dw, ybase), col, -1)
                cv2.rectangle(img, _ip(x, ybase - dh), _ip(x + dw, ybase), frame, max(1, int(0.06 * ppm)))
                if rng.random() < 0.6:
                    _poster(img, rng, x - 0.2 * ppm, ybase - dh - 0.6 * ppm, dw + 0.4 * ppm, 0.45 * ppm)
                x += dw + rng.uniform(0.5, 2.0) * ppm
                continue
            glass = _rgb(rng, (0.1, 0.6), (0.1, 0.95), 0.6 if rng.random() < 0.6 else 0.12, 0.06)
            cv2.rectangle(img, _ip(x, y0), _ip(x + ww, y0 + wh), glass, -1)
            if rng.random() < 0.5:  # curtain
                cv2.rectangle(img, _ip(x, y0), _ip(x + ww * rng.uniform(0.2, 0.6), y0 + wh), _rgb(rng), -1)
            cv2.rectangle(img, _ip(x, y0), _ip(x + ww, y0 + wh), frame, max(1, int(0.08 * ppm)))
            if rng.random() < 0.6:
                cv2.line(img, _ip(x + ww / 2, y0), _ip(x + ww / 2, y0 + wh), frame, max(1, int(0.05 * ppm)))
            cv2.rectangle(img, _ip(x - 2, y0 + wh), _ip(x + ww + 2, y0 + wh + 0.06 * ppm), (200, 200, 195), -1)
            x += ww + rng.uniform(0.5, 2.5) * ppm
    for _ in range(int(rng.integers(0, 4))):  # signs
        sw, sh = rng.uniform(0.8, 3.0) * ppm, rng.uniform(0.3, 0.8) * ppm
        x, y = rng.uniform(0, max(1, w - sw)), rng.uniform(0.2 * h, max(0.2 * h, h - 2.5 * ppm))
        bg = _rgb(rng, (0.3, 1), (0.3, 1))
        cv2.rectangle(img, _ip(x, y), _ip(x + sw, y + sh), bg, -1)
        _text(img, rng, x + 0.05 * sw, y + 0.75 * sh, 0.5 * sh, _contrast(bg, rng), 0.9 * sw)
    _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.3)) + 2, (0.1 * ppm, 0.5 * ppm),
                    ((0.3, 1), (0.2, 0.9),))
    return img


def _paint_roof(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    cols = [_rgb(rng, (0.1, 0.5), (0.15, 0.45)) for _ in range(3)]
    img = _material(rng, h, w, ppm, cols, scale_m=1.0, blotch=0.5, grain=16)
    _scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.3)) + 2, (0.2 * ppm, 0.8 * ppm),
                    ((0, 0.3), (0.3, 0.9),))
    return img


def _paint_ground(rng: np.random.Generator, size: int, ppm: float) -> np.ndarray:
    """Tileable ground (grass, dirt patches, stones, flowers, a path) ``(size, size, 3)`` uint8."""
    hue = rng.uniform(0.17, 0.33)
    grass = [np.array(_rgb(rng, (0.35, 0.8), (0.25, 0.6), hue, 0.04), _F32) for _ in range(3)]
    dirt = np.array(_rgb(rng, (0.3, 0.6), (0.3, 0.6), 0.08, 0.03), _F32)
    half = size // 2  # the smooth colour fields are composed at half resolution, then upsampled
    n1 = _fbm(rng, half, half, 128, 6, 0.6, wrap=True)
    n2 = _fbm(rng, half, half, 64, 4, 0.6, wrap=True)
    n3 = _fbm(rng, half, half, 256, 4, 0.5, wrap=True)
    low = _mix(grass[0], grass[1], np.clip(0.5 + 0.35 * n1, 0, 1)[..., None])
    low = _mix(low, grass[2], np.clip((n2 - 0.3) * 3, 0, 1)[..., None] * 0.8)
    low = _mix(low, dirt, np.clip((n3 - rng.uniform(0.3, 1.0)) * 2.5, 0, 1)[..., None])
    low = np.pad(low, ((1, 1), (1, 1), (0, 0)), mode="wrap")
    img = cv2.resize(low, ((half + 2) * 2, (half + 2) * 2), interpolation=cv2.INTER_LINEAR)[2 : 2 + size, 2 : 2 + size]
    img += 22 * rng.standard_normal((size, size, 1), dtype=_F32)
    img = np.clip(img, 0, 255).astype(np.uint8)

    def draw(canvas: np.ndarray) -> None:
        ch, cw = canvas.shape[:2]
        pts = [np.array([rng.uniform(0, cw), rng.uniform(0, ch)])]
        for _ in range(60):  # a winding path
            pts.append(pts[-1] + rng.normal(0, 0.8 * ppm, 2))
        cv2.polylines(canvas, [np.array(pts).astype(np.int32)], False, tuple(int(c) for c in dirt * 1.1),
                      int(rng.uniform(0.6, 1.2) * ppm), cv2.LINE_AA)
        n = int(ch * cw / ppm**2 * 1.2)
        _scatter_shapes(canvas, rng, n, (0.02 * ppm, 0.15 * ppm), ((0, 0.2), (0.3, 0.85),), outline=0.8)
        _scatter_shapes(canvas, rng, n, (0.01 * ppm, 0.03 * ppm), ((0.5, 1.0), (0.7, 1.0),))
        _scatter_shapes(canvas, rng, n // 2, (0.03 * ppm, 0.08 * ppm), ((0.5, 0.9), (0.15, 0.45), hue, 0.06))

    _wrap_draw(img, draw, margin=int(ppm))
    return img


def _paint_clouds(rng: np.random.Generator, size: int, coverage: float) -> np.ndarray:
    """Tileable cloud alpha ``(size, size)`` float32 in [0, 1]."""
    n = _fbm(rng, size, size, size // 4, 8, 0.58, wrap=True)
    thr = 1.2 - 2.0 * coverage
    return np.clip((n - thr) * 1.3, 0, 1).astype(_F32)


# ----------------------------------------------------------------------------------------------------
# ray casting
# ----------------------------------------------------------------------------------------------------
class _Surface:
    def __init__(self, tex: np.ndarray, ppm: float, size_m: tuple[float, float], shade: float = 1.0,
                 ao: float = 0.0, fog: float = math.inf, wrap: bool = False) -> None:
        self.tex, self.ppm, self.size_m, self.shade, self.ao, self.fog, self.wrap = tex, ppm, size_m, shade, ao, fog, wrap


class _Caster:
    """Per-pixel nearest hit ``(t, surface id, u, v)`` over planes and boxes (flat arrays, float32)."""

    def __init__(self, width: int) -> None:
        W, H = width, width // 2
        self.W, self.H = W, H
        lon = ((np.arange(W, dtype=np.float64) + 0.5) / W - 0.5) * 2 * np.pi
        lat = (0.5 - (np.arange(H, dtype=np.float64) + 0.5) / H) * np.pi
        cl = np.cos(lat)[:, None]
        self.lat_deg = np.degrees(lat).astype(_F32)
        self.d = [
            (cl * np.sin(lon)[None, :]).astype(_F32).ravel(),
            np.repeat(np.sin(lat), W).astype(_F32),
            (cl * np.cos(lon)[None, :]).astype(_F32).ravel(),
        ]
        with np.errstate(divide="ignore"):
            self.inv = [np.where(np.abs(a) > 1e-9, 1.0 / a, np.float32(1e9)).astype(_F32) for a in self.d]
        n = W * H
        self.t = np.full(n, np.inf, _F32)
        self.sid = np.full(n, -1, np.int32)
        self.u = np.zeros(n, _F32)
        self.v = np.zeros(n, _F32)
        self.cos = np.ones(n, _F32)
        self.surfaces: list[_Surface] = []

    def add_surface(self, s: _Surface) -> int:
        self.surfaces.append(s)
        return len(self.surfaces) - 1

    def _assign(self, idx: np.ndarray, t: np.ndarray, sid: int, uspec: tuple, vspec: tuple, axis: int) -> None:
        """Record hits ``idx`` at distance ``t``; ``u = s * (p[a] - o)`` for ``uspec = (a, s, o)``."""
        self.t[idx] = t
        self.sid[idx] = sid
        p = {}
        for a in {uspec[0], vspec[0]}:
            p[a] = t * self.d[a][idx]
        self.u[idx] = uspec[1] * (p[uspec[0]] - uspec[2])
        self.v[idx] = vspec[1] * (p[vspec[0]] - vspec[2])
        self.cos[idx] = np.abs(self.d[axis][idx])

    def room(self, lo: Sequence[float], hi: Sequence[float], sids: dict[str, int]) -> None:
        """Inside of the box ``[lo, hi]`` (camera at the origin, inside)."""
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        t_axis = [np.where(self.d[a] > 0, hi[a], lo[a]).astype(_F32) * self.inv[a] for a in range(3)]
        t = np.minimum(np.minimum(t_axis[0], t_axis[1]), t_axis[2])
        axis = np.where(t == t_axis[0], 0, np.where(t == t_axis[1], 1, 2))
        faces = {
            # name: (axis, positive side, uspec, vspec)
            "front": (2, True, (0, 1, x0), (1, -1, y1)),
            "back": (2, False, (0, -1, x1), (1, -1, y1)),
            "right": (0, True, (2, -1, z1), (1, -1, y1)),
            "left": (0, False, (2, 1, z0), (1, -1, y1)),
            "ceiling": (1, True, (0, 1, x0), (2, 1, z0)),
            "floor": (1, False, (0, 1, x0), (2, -1, z1)),
        }
        for name, (a, pos, us, vs) in faces.items():
            idx = np.flatnonzero((axis == a) & ((self.d[a] > 0) == pos))
            self._assign(idx, t[idx], sids[name], us, vs, a)

    def plane_y(self, y: float, sid: int, origin: tuple[float, float]) -> None:
        """The infinite horizontal plane at height ``y`` (< 0: ground, seen from above)."""
        down = self.d[1] < 0 if y < 0 else self.d[1] > 0
        t = np.where(down, y * self.inv[1], np.inf).astype(_F32)
        idx = np.flatnonzero(t < self.t)
        self._assign(idx, t[idx], sid, (0, 1, origin[0]), (2, -1, origin[1]), 1)

    def _region(self, lo: Sequence[float], hi: Sequence[float]) -> np.ndarray | None:
        """Flat pixel indices that may see the box ``[lo, hi]`` (its lon/lat bounding rectangle), or
        ``None`` for the whole panorama (camera above / below the box)."""
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        if x0 <= 0 <= x1 and z0 <= 0 <= z1:
            return None
        corners = [(x, z) for x in (x0, x1) for z in (z0, z1)]
        lc = math.atan2((x0 + x1) / 2, (z0 + z1) / 2)
        half = max(abs((math.atan2(x, z) - lc + math.pi) % (2 * math.pi) - math.pi) for x, z in corners)
        dmin = math.hypot(max(x0, 0.0, -x1), max(z0, 0.0, -z1))
        dmax = max(math.hypot(x, z) for x, z in corners)
        lat_hi = math.atan2(y1, dmin if y1 >= 0 else dmax)
        lat_lo = math.atan2(y0, dmin if y0 <= 0 else dmax)
        W, H = self.W, self.H
        u0 = math.floor(((lc - half) / (2 * math.pi) + 0.5) * W - 0.5) - 1
        u1 = math.ceil(((lc + half) / (2 * math.pi) + 0.5) * W - 0.5) + 1
        cols = np.arange(W) if u1 - u0 + 1 >= W else np.arange(u0, u1 + 1) % W
        r0 = max(0, math.floor((0.5 - lat_hi / math.pi) * H - 0.5) - 1)
        r1 = min(H - 1, math.ceil((0.5 - lat_lo / math.pi) * H - 0.5) + 1)
        return (np.arange(r0, r1 + 1)[:, None] * W + cols[None, :]).ravel()

    def box(self, lo: Sequence[float], hi: Sequence[float], sids: dict[int, int]) -> None:
        """Outside of the box ``[lo, hi]`` (camera outside). ``sids[axis]``: the texture of the face
        of that axis facing the camera (omit axes whose faces cannot be seen)."""
        region = self._region(lo, hi)
        if region is None:
            region = np.arange(self.t.size)
        near = []
        far = []
        for a in range(3):
            inv = self.inv[a][region]
            t1, t2 = lo[a] * inv, hi[a] * inv
            near.append(np.minimum(t1, t2))
            far.append(np.maximum(t1, t2))
        tmin = np.maximum(np.maximum(near[0], near[1]), near[2])
        tmax = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (tmin <= tmax) & (tmin > 1e-4) & (tmin < self.t[region])
        axis = np.where(tmin == near[0], 0, np.where(tmin == near[1], 1, 2))
        x0, y0, z0 = lo
        x1, y1, z1 = hi
        for a, sid in sids.items():
            sel = np.flatnonzero(hit & (axis == a))
            if sel.size == 0:
                continue
            if a == 0:
                us = (2, -1, z1) if x0 > 0 else (2, 1, z0)
                vs = (1, -1, y1)
            elif a == 2:
                us = (0, 1, x0) if z0 > 0 else (0, -1, x1)
                vs = (1, -1, y1)
            else:
                us, vs = (0, 1, x0), (2, 1, z0)
            self._assign(region[sel], tmin[sel], sid, us, vs, a)

    # -------------------------------------------------------------------------------------------
    def shade(self) -> tuple[np.ndarray, np.ndarray]:
        """Colours ``(N, 3)`` float32 of the hit pixels and the hit mask ``(N,)``."""
        n = self.t.size
        hit = self.sid >= 0
        out = np.zeros((n, 3), _F32)
        if not hit.any():
            return out, hit
        pad = 8
        # shelf-pack the textures into one atlas (positions multiples of 4 for the mip levels)
        texs = [s.tex for s in self.surfaces]
        order = sorted(range(len(texs)), key=lambda i: -texs[i].shape[0])
        aw = max(2048, max(t.shape[1] for t in texs) + 2 * pad)
        aw = (aw + 3) // 4 * 4
        pos = [(0, 0)] * len(texs)
        x = y = shelf = 0
        for i in order:
            th, tw = texs[i].shape[:2]
            bw, bh = (tw + 2 * pad + 3) // 4 * 4, (th + 2 * pad + 3) // 4 * 4
            if x + bw > aw:
                x, y, shelf = 0, y + shelf, 0
            pos[i] = (x + pad, y + pad)
            x += bw
            shelf = max(shelf, bh)
        ah = (y + shelf + 3) // 4 * 4
        if max(aw, ah) >= 32000:
            raise RuntimeError("synthetic texture atlas too large")
        atlas = np.zeros((ah, aw, 3), np.uint8)
        for i, tex in enumerate(texs):
            px, py = pos[i]
            mode = "wrap" if self.surfaces[i].wrap else "edge"
            atlas[py - pad : py + tex.shape[0] + pad, px - pad : px + tex.shape[1] + pad] = np.pad(
                tex, ((pad, pad), (pad, pad), (0, 0)), mode=mode
            )
        sid = np.where(hit, self.sid, 0)
        ppm = np.array([s.ppm for s in self.surfaces], _F32)[sid]
        tw = np.array([t.shape[1] for t in texs], _F32)[sid]
        th = np.array([t.shape[0] for t in texs], _F32)[sid]
        wrap = np.array([s.wrap for s in self.surfaces], bool)[sid]
        ox = np.array([p[0] for p in pos], _F32)[sid]
        oy = np.array([p[1] for p in pos], _F32)[sid]
        tx = self.u * ppm - 0.5
        ty = self.v * ppm - 0.5
        tx = np.where(wrap, np.mod(tx, tw), np.clip(tx, 0, tw - 1)) + ox
        ty = np.where(wrap, np.mod(ty, th), np.clip(ty, 0, th - 1)) + oy
        # mip level from the pixel footprint in texels
        foot = np.where(hit, self.t, 0) * (np.pi / self.H) * ppm / np.sqrt(np.maximum(self.cos, 0.3))
        level = np.clip(np.log2(np.maximum(foot, 1e-6)), 0, _MIP_LEVELS - 1 - 1e-3).astype(_F32)
        lo_l = np.floor(level)
        frac = (level - lo_l)[:, None]
        mips = [atlas]
        for _ in range(_MIP_LEVELS - 1):
            mips.append(cv2.pyrDown(mips[-1]))
        samples = []
        for lvl, img in enumerate(mips):
            s = 2.0**lvl
            mx = ((tx + 0.5) / s - 0.5).reshape(self.H, self.W)
            my = ((ty + 0.5) / s - 0.5).reshape(self.H, self.W)
            samples.append(cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3))
        for lvl in range(_MIP_LEVELS):
            w = np.where(lo_l == lvl, 1 - frac[:, 0], 0) + np.where(lo_l == lvl - 1, frac[:, 0], 0)
            out += samples[lvl].astype(_F32) * w[:, None]
        # shading: per-surface factor, darkening near the surface edges (ambient occlusion)
        shade = np.array([s.shade for s in self.surfaces], _F32)[sid]
        ao = np.array([s.ao for s in self.surfaces], _F32)[sid]
        su = np.array([s.size_m[0] for s in self.surfaces], _F32)[sid]
        sv = np.array([s.size_m[1] for s in self.surfaces], _F32)[sid]
        with np.errstate(invalid="ignore"):
            edge = np.minimum(np.minimum(self.u, su - self.u), np.minimum(self.v, sv - self.v))
        edge = np.where(np.isfinite(edge), np.maximum(edge, 0), 1e3)
        out *= (shade * (1 - ao * np.exp(-edge / 0.3)))[:, None]
        self.fog = np.array([s.fog for s in self.surfaces], _F32)[sid]
        return out, hit


# ----------------------------------------------------------------------------------------------------
# scenes
# ----------------------------------------------------------------------------------------------------
def _ppm_for(distance: float, height: int, lo: float = 12.0, hi: float = 100.0) -> float:
    """Texels per metre so that a texel is about 0.8 panorama pixels at ``distance`` metres."""
    return float(np.clip(1.0 / (0.8 * max(distance, 0.05) * math.pi / height), lo, hi))


def _tex_size(size_m: float, ppm: float) -> int:
    return max(8, int(math.ceil(size_m * ppm)))


def _place_boxes(rng: np.random.Generator, n: int, bounds: tuple[float, float, float, float],
                 size: tuple[float, float], height: tuple[float, float], clear: float,
                 wall_snap: float = 0.0) -> list[tuple[list[float], list[float]]]:
    """``n`` axis-aligned footprints inside ``bounds = (x0, x1, z0, z1)`` keeping the camera (origin)
    ``clear`` metres away; returns ``(lo_xz, hi_xz, height)`` tuples."""
    x0b, x1b, z0b, z1b = bounds
    out = []
    for _ in range(n * 20):
        if len(out) >= n:
            break
        sx, sz = rng.uniform(*size), rng.uniform(*size)
        if rng.random() < 0.5:
            sx *= rng.uniform(0.3, 0.6)
        x = rng.uniform(x0b, max(x0b, x1b - sx))
        z = rng.uniform(z0b, max(z0b, z1b - sz))
        if rng.random() < wall_snap:
            side = int(rng.integers(4))
            if side == 0:
                x = x0b
            elif side == 1:
                x = x1b - sx
            elif side == 2:
                z = z0b
            else:
                z = z1b - sz
        # distance from the origin to the footprint rectangle
        dx = max(x - 0, 0, 0 - (x + sx))
        dz = max(z - 0, 0, 0 - (z + sz))
        if math.hypot(dx, dz) < clear:
            continue
        out.append(([x, z], [x + sx, z + sz], rng.uniform(*height)))
    return out


def _box_faces(caster: _Caster, lo: list[float], hi: list[float], H: int, paint: Callable[[int, int, float, bool], np.ndarray],
               shades: tuple[float, float, float], ao: float, fog: float) -> dict[int, int]:
    """Surfaces of the (at most 3) faces of box ``[lo, hi]`` facing the camera at the origin."""
    sids = {}
    for a in range(3):
        if lo[a] > 0:
            dist = lo[a]
        elif hi[a] < 0:
            dist = -hi[a]
        else:
            continue
        if a == 1:
            su, sv = hi[0] - lo[0], hi[2] - lo[2]
        elif a == 0:
            su, sv = hi[2] - lo[2], hi[1] - lo[1]
        else:
            su, sv = hi[0] - lo[0], hi[1] - lo[1]
        # nearest point of the face to the camera, for the texture resolution
        q = [min(max(0.0, lo[k]), hi[k]) for k in range(3)]
        q[a] = lo[a] if lo[a] > 0 else hi[a]
        dist = math.sqrt(sum(c * c for c in q))
        ppm = _ppm_for(dist, H)
        tex = paint(_tex_size(su, ppm), _tex_size(sv, ppm), ppm, a == 1)
        sids[a] = caster.add_surface(_Surface(tex, ppm, (su, sv), shades[a], ao, fog))
    return sids


def _indoor(rng: np.random.Generator, width: int, big: bool) -> np.ndarray:
    st = _Style(rng, outdoor=False)
    caster = _Caster(width)
    H = caster.H
    eye = rng.uniform(1.4, 1.7)
    if big:
        x0, x1 = -rng.uniform(3.5, 8), rng.uniform(3.5, 8)
        z0, z1 = -rng.uniform(3, 7), rng.uniform(3, 7)
        height = rng.uniform(3.4, 5.0)
    else:
        x0, x1 = -rng.uniform(1.5, 3.5), rng.uniform(1.5, 3.5)
        z0, z1 = -rng.uniform(1.5, 3.5), rng.uniform(1.5, 3.5)
        height = rng.uniform(2.5, 3.2)
    y0, y1 = -eye, height - eye
    lo, hi = (x0, y0, z0), (x1, y1, z1)
    sids = {}
    walls = {"front": (x1 - x0, z1), "back": (x1 - x0, -z0), "right": (z1 - z0, x1), "left": (z1 - z0, -x0)}
    for name, (wm, dist) in walls.items():
        ppm = _ppm_for(dist, H, hi=90)
        tex = _paint_wall(rng, st, _tex_size(wm, ppm), _tex_size(height, ppm), ppm, big)
        sids[name] = caster.add_surface(_Surface(tex, ppm, (wm, height), rng.uniform(0.82, 1.0), 0.35))
    ppm = _ppm_for(eye, H, hi=90)
    sids["floor"] = caster.add_surface(
        _Surface(_paint_floor(rng, st, _tex_size(x1 - x0, ppm), _tex_size(z1 - z0, ppm), ppm), ppm, (x1 - x0, z1 - z0), 0.9, 0.4)
    )
    ppm = _ppm_for(y1, H, hi=90)
    sids["ceiling"] = caster.add_surface(
        _Surface(_paint_ceiling(rng, st, _tex_size(x1 - x0, ppm), _tex_size(z1 - z0, ppm), ppm), ppm, (x1 - x0, z1 - z0), 0.95, 0.4)
    )
    caster.room(lo, hi, sids)
    n = int(rng.integers(6, 13)) if big else int(rng.integers(3, 7))
    boxes = _place_boxes(rng, n, (x0 + 0.05, x1 - 0.05, z0 + 0.05, z1 - 0.05),
                         (0.4, 3.0 if big else 1.8), (0.4, min(2.4, height - 0.2)), 0.7, wall_snap=0.5)
    for (bx0, bz0), (bx1, bz1), bh in boxes:
        blo, bhi = [bx0, y0, bz0], [bx1, y0 + bh, bz1]

        def paint(w: int, h: int, ppm: float, top: bool) -> np.ndarray:
            if not top and rng.random() < 0.3 and h > 0.8 * ppm:
                img = _paint_furniture(rng, st, w, h, ppm, False)
                _bookshelf(img, rng, 0, 0, w, h, ppm)
                return img
            return _paint_furniture(rng, st, w, h, ppm, top)

        fs = _box_faces(caster, blo, bhi, H, paint, (rng.uniform(0.7, 0.9), 1.0, rng.uniform(0.75, 0.95)), 0.25, math.inf)
        caster.box(blo, bhi, fs)
    col, hit = caster.shade()
    return np.clip(col, 0, 255).astype(np.uint8).reshape(H, width, 3)


def _outdoor(rng: np.random.Generator, width: int, village: bool) -> np.ndarray:
    caster = _Caster(width)
    H, W = caster.H, width
    eye = rng.uniform(1.5, 1.8)
    sun_az, sun_el = rng.uniform(-np.pi, np.pi), rng.uniform(np.radians(20), np.radians(60))
    sun = np.array([np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el), np.cos(sun_el) * np.cos(sun_az)])
    haze = np.array(_rgb(rng, (0.05, 0.25), (0.75, 0.95), 0.58, 0.05), _F32)
    fog = rng.uniform(120, 400)
    # ground: a tileable 32 m texture
    gsize, gppm = 1536, 48.0
    ground = caster.add_surface(_Surface(_paint_ground(rng, gsize, gppm), gppm, (math.inf, math.inf), 1.0, 0.0, fog, wrap=True))
    caster.plane_y(-eye, ground, (rng.uniform(0, 32), rng.uniform(0, 32)))

    def face_shade(a: int, lo: list[float], hi: list[float]) -> float:
        n = np.zeros(3)
        n[a] = -1.0 if lo[a] > 0 else 1.0
        return float(0.55 + 0.45 * max(0.0, float(n @ sun)))

    objects = []
    if village:
        objects += [("house", b) for b in _place_boxes(rng, int(rng.integers(6, 14)), (-60, 60, -60, 60), (5, 14), (3, 13), 7)]
        objects += [("crate", b) for b in _place_boxes(rng, int(rng.integers(4, 10)), (-25, 25, -25, 25), (0.6, 4), (0.5, 2.2), 2.5)]
    objects += [("rock", b) for b in _place_boxes(rng, int(rng.integers(6, 16)), (-40, 40, -40, 40), (0.4, 4), (0.3, 2.5), 2.0)]
    if rng.random() < 0.7:  # a stone wall
        objects += [("rock", b) for b in _place_boxes(rng, 1, (-30, 30, -30, 30), (6, 20), (0.6, 1.4), 3.0)]
    for kind, ((bx0, bz0), (bx1, bz1), bh) in objects:
        blo, bhi = [bx0, -eye, bz0], [bx1, -eye + bh, bz1]

        def paint(w: int, h: int, ppm: float, top: bool, kind: str = kind) -> np.ndarray:
            if kind == "house":
                return _paint_roof(rng, w, h, ppm) if top else _paint_facade(rng, w, h, ppm)
            if kind == "crate":
                return _paint_furniture(rng, _Style(rng, True), w, h, ppm, top)
            return _paint_rock(rng, w, h, ppm)

        shades = tuple(face_shade(a, blo, bhi) for a in range(3))
        fs = _box_faces(caster, blo, bhi, H, paint, shades, 0.15, fog)  # type: ignore[arg-type]
        caster.box(blo, bhi, fs)

    col, hit = caster.shade()
    # aerial perspective on the hits
    f = (1.0 - np.exp(-np.where(hit, caster.t, 0) / caster.fog))[:, None]
    col = col * (1 - f) + haze * f

    # background (functions of the direction only): sky, sun, clouds, mountains. Only the rows at or
    # above the horizon can miss the ground, so only those are computed.
    nb = int(np.count_nonzero(caster.lat_deg >= 0))
    m = nb * W
    lat = caster.lat_deg[:nb]
    dx, dy, dz = (d[:m] for d in caster.d)
    zenith = np.array(_rgb(rng, (0.45, 0.8), (0.55, 0.85), 0.6, 0.04), _F32)
    sky = _mix(haze, zenith, (np.clip(dy, 0, 1) ** 0.6)[:, None])
    cosang = dx * sun[0] + dy * sun[1] + dz * sun[2]
    glow = (np.clip(cosang, 0, 1) ** 300 * 0.6 + (cosang > math.cos(math.radians(1.5))) * 0.8).astype(_F32)
    sky += glow[:, None] * (np.array([255, 250, 230], _F32) - sky)
    # clouds on a plane 1.5 km up, 8 m per texel, tileable, 5 mip levels; faded out near the horizon
    csize, cm = 1024, 8.0
    alpha_tex = _paint_clouds(rng, csize, rng.uniform(0.25, 0.65))
    shade_tex = 0.78 + 0.22 * np.clip(0.5 + 0.3 * _fbm(rng, csize, csize, 64, 5, wrap=True), 0, 1)
    mip = np.stack([alpha_tex, shade_tex.astype(_F32)], -1)
    rc = int(np.count_nonzero(lat > 1.0))  # rows that can show clouds
    if rc > 0:
        up = np.maximum(dy[: rc * W], 0.01)
        tc = 1500.0 / up
        cx = (tc * dx[: rc * W] / cm).reshape(rc, W)
        cz = (tc * dz[: rc * W] / cm).reshape(rc, W)
        lvl = np.clip(np.log2(np.maximum(tc * (np.pi / H) / cm, 1e-6)), 0, 4).reshape(rc, W)
        c_acc = np.zeros((rc, W, 2), _F32)
        for k in range(5):
            sc = 2.0**k
            wgt = np.clip(1 - np.abs(lvl - k), 0, 1)
            if wgt.any():
                mx = np.mod(cx / sc, mip.shape[1]).astype(_F32)
                mz = np.mod(cz / sc, mip.shape[0]).astype(_F32)
                c_acc += cv2.remap(mip, mx, mz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP) * wgt[..., None]
            mip = cv2.pyrDown(np.pad(mip, ((2, 2), (2, 2), (0, 0)), mode="wrap"))[1:-1, 1:-1]
        alpha = (c_acc[..., 0] * np.clip((lat[:rc, None] - 1.0) / 10.0, 0, 1)).reshape(-1, 1)
        cloud_col = np.array([252, 252, 250], _F32) * c_acc[..., 1].reshape(-1, 1)
        sky[: rc * W] = sky[: rc * W] * (1 - alpha) + cloud_col * alpha
    bg = sky.reshape(nb, W, 3)
    # mountains: 3 ridgelines (far to near) at infinity, on the band of rows just above the horizon
    layer_col = [np.array(_rgb(rng, (0.1, 0.5), (0.25, 0.6), rng.uniform(0.2, 0.6), 0.1), _F32) for _ in range(3)]
    elevs = []
    for k in range(3):
        cell = max(1, W // 8)
        prof = _fbm(rng, cell, W, cell, 7, 0.55, wrap=True)[0]
        ridge = 1 - np.abs(prof) / (np.abs(prof).max() + 1e-6)
        elevs.append((rng.uniform(1.5, 4) + rng.uniform(6, 22 - 5 * k) * ridge**1.5).astype(_F32))
    r0 = int(np.count_nonzero(lat > max(float(e.max()) for e in elevs) + 0.5))
    band = bg[r0:nb]
    bh = nb - r0
    if bh > 0:
        rock = _fbm(rng, bh, W, max(2, W // 256), 6, 0.6, wrap=True)
        detail = rng.standard_normal((bh, W), dtype=_F32)
        lat2 = lat[r0:nb, None]
        for k in range(3):
            elev = elevs[k][None, :]
            mask = lat2 < elev
            c = layer_col[k] * (0.7 + 0.16 * rock + 0.1 * detail)[..., None]
            snowline = float(elevs[k].max()) * rng.uniform(0.55, 0.9)
            if k < 2:
                snow = lat2 > snowline + 1.5 * rock
                c = np.where(snow[..., None], np.array([240, 240, 245], _F32) * (0.85 + 0.08 * rock[..., None]), c)
            h_fog = ((0.65 - 0.25 * k) + 0.25 * np.clip(1 - lat2 / np.maximum(elev, 1e-3), 0, 1))[..., None]
            c = c * (1 - h_fog) + haze * h_fog
            band = np.where(mask[..., None], c, band)
        bg[r0:nb] = band
    out = col.reshape(H, W, 3)
    out[:nb] = np.where(hit[:m, None], col[:m], bg.reshape(-1, 3)).reshape(nb, W, 3)
    return np.clip(out, 0, 255).astype(np.uint8)


def generate_panorama(seed: int, kind: str = "room", width: int = 1024) -> np.ndarray:
    """Ray-cast one procedural equirectangular panorama.

    Args:
        seed: any int; the image is a deterministic function of ``(seed, kind, width)``.
        kind: one of :data:`SCENE_KINDS` (``room``, ``hall``, ``landscape``, ``village``).
        width: panorama width ``We`` in pixels (even, >= 64); the height is ``We / 2``.

    Returns:
        ``(width // 2, width, 3)`` RGB uint8 array; column ``u`` looks at longitude
        ``(u + 0.5) / We * 360 - 180`` degrees, row ``v`` at latitude ``90 - (v + 0.5) / He * 180``.
    """
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown synthetic scene kind {kind!r}; valid: {', '.join(SCENE_KINDS)}")
    width = int(width)
    if width < 64 or width % 2:
        raise ValueError(f"synthetic panorama width must be an even number >= 64, got {width}")
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, SCENE_KINDS.index(kind), 0x53594E54])
    if kind in ("room", "hall"):
        return _indoor(rng, width, big=kind == "hall")
    return _outdoor(rng, width, village=kind == "village")


# ----------------------------------------------------------------------------------------------------
# the on-disk data set
# ----------------------------------------------------------------------------------------------------
def synthetic_image_seed(seed: int, index: int) -> int:
    """Seed of the ``index``-th image of a synthetic data set with master ``seed``."""
    return (int(seed) * 1_000_003 + int(index) * 7919 + 17) & 0x7FFFFFFF


def ensure_synthetic_images(
    root: str | os.PathLike,
    num_images: int = 40,
    seed: int = 0,
    width: int = 1024,
    labels: Sequence[str] = SCENE_KINDS,
    progress: bool = True,
    workers: int | None = None,
) -> list[ImageEntry]:
    """Generate (once) the synthetic data set under ``root`` and return its images.

    Image ``i`` has label ``labels[i % len(labels)]`` (each label must be a scene kind), seed
    :func:`synthetic_image_seed` ``(seed, i)`` and lives at ``<root>/<label>/synth_<i:04d>.jpg``
    (JPEG quality 95). ``<root>/synthetic.json`` records the parameters; when it matches and all files
    exist nothing is generated, otherwise the set is regenerated (stale ``synth_*`` files removed).
    """
    root = Path(os.path.abspath(os.path.expanduser(root)))
    labels = [str(x) for x in labels]
    bad = [x for x in labels if x not in SCENE_KINDS]
    if not labels or bad:
        raise DatasetError(f"synthetic labels must be scene kinds from {', '.join(SCENE_KINDS)}, got {list(labels)}")
    if int(num_images) < 1:
        raise DatasetError(f"synthetic num_images must be >= 1, got {num_images}")
    params = {"version": GENERATOR_VERSION, "num_images": int(num_images), "seed": int(seed),
              "width": int(width), "labels": labels}
    files = [(f"{labels[i % len(labels)]}/synth_{i:04d}.jpg", labels[i % len(labels)]) for i in range(int(num_images))]
    entries = [ImageEntry(str(root / rel), label) for rel, label in files]
    manifest = root / MANIFEST
    if manifest.is_file():
        try:
            old = read_json(manifest, "synthetic manifest")
        except (ValueError, OSError):
            old = None
        if isinstance(old, dict) and old.get("params") == params and all(Path(e.path).is_file() for e in entries):
            return entries
    keep = {str(root / rel) for rel, _ in files}
    if root.is_dir():
        for stale in root.glob("*/synth_*.jpg"):
            if str(stale) not in keep:
                stale.unlink()
    def make(i: int) -> None:
        rel, label = files[i]
        img = generate_panorama(synthetic_image_seed(seed, i), label, width)
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])
        if not ok:  # pragma: no cover
            raise DatasetError(f"could not encode synthetic image {rel}")
        atomic_write(root / rel, lambda tmp: buf.tofile(tmp))

    workers = max(1, workers or min(4, os.cpu_count() or 1))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(files), desc="generating synthetic panoramas", unit="img", leave=False)
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for _ in pool.map(make, range(len(files))):
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    write_json(manifest, {"params": params, "images": [{"image": rel, "label": label} for rel, label in files]})
    return entries
