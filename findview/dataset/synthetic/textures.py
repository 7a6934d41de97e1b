"""Texture primitives for the synthetic panoramas: value noise, random colours, drawing helpers.

Everything works in texel units on RGB ``uint8`` images (``(h, w, 3)``) or float32 fields (``(h, w)``),
and draws only from the ``numpy.random.Generator`` it is given, so a texture is a deterministic function
of the generator state. The surface painters (:mod:`findview.dataset.synthetic.painters`) compose these.
"""

from __future__ import annotations

import colorsys
from typing import Callable, Sequence

import cv2
import numpy as np

__all__ = [
    "F32", "FONTS", "CHARS", "value_noise", "fbm", "random_rgb", "random_rgbs", "lerp", "base_material", "ipt",
    "contrast_rgb", "draw_text", "draw_pixel_art", "draw_poster", "draw_bookshelf", "scatter_shapes", "wrap_draw",
]


F32 = np.float32
FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
    cv2.FONT_HERSHEY_SCRIPT_SIMPLEX,
)
CHARS = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijkmnopqrstuvwxyz0123456789 #&+-%@"))


# ----------------------------------------------------------------------------------------------------
# noise and colours
# ----------------------------------------------------------------------------------------------------
def value_noise(rng: np.random.Generator, h: int, w: int, cell: float, wrap: bool = False) -> np.ndarray:
    """Smooth value noise ``(h, w)`` float32 (lattice spacing ``cell`` texels, unit-variance lattice).

    With ``wrap`` the result tiles seamlessly when ``h`` and ``w`` are multiples of ``cell`` (otherwise
    it silently does not wrap).
    """
    cell = max(1, int(round(cell)))
    if cell == 1:
        return rng.standard_normal((h, w), dtype=F32)
    if wrap and h % cell == 0 and w % cell == 0:
        gh, gw = h // cell, w // cell
        g = np.pad(rng.standard_normal((gh, gw), dtype=F32), 2, mode="wrap")
        big = cv2.resize(g, ((gw + 4) * cell, (gh + 4) * cell), interpolation=cv2.INTER_CUBIC)
        return np.ascontiguousarray(big[2 * cell : 2 * cell + h, 2 * cell : 2 * cell + w])
    gh, gw = h // cell + 4, w // cell + 4
    g = rng.standard_normal((gh, gw), dtype=F32)
    big = cv2.resize(g, (gw * cell, gh * cell), interpolation=cv2.INTER_CUBIC)
    oy, ox = (int(v) for v in rng.integers(cell, 2 * cell, size=2))
    return np.ascontiguousarray(big[oy : oy + h, ox : ox + w])


def fbm(
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
    out = np.zeros((h, w), F32)
    if low:
        if wrap:
            hl, wl = h // 4, w // 4
            acc = sum(a * value_noise(rng, hl, wl, c / 4, True) for c, a in low)
            acc = np.pad(acc, 1, mode="wrap")
            out += cv2.resize(acc, ((wl + 2) * 4, (hl + 2) * 4), interpolation=cv2.INTER_LINEAR)[4 : 4 + h, 4 : 4 + w]
        else:
            hl, wl = h // 4 + 2, w // 4 + 2
            acc = sum(a * value_noise(rng, hl, wl, c / 4, False) for c, a in low)
            out += cv2.resize(acc, (wl * 4, hl * 4), interpolation=cv2.INTER_LINEAR)[:h, :w]
    for c, a in octs:
        if (c, a) not in low:
            out += a * value_noise(rng, h, w, c, wrap)
    out -= out.mean()
    out /= out.std() + 1e-6
    return out


def random_rgb(rng: np.random.Generator, s: tuple[float, float] = (0.2, 0.8), v: tuple[float, float] = (0.3, 0.9),
         hue: float | None = None, hue_jitter: float = 1.0) -> tuple[int, int, int]:
    """A random colour (RGB ints 0..255) from HSV ranges; ``hue`` in [0, 1) with ``hue_jitter`` spread."""
    hh = rng.random() if hue is None else (hue + rng.uniform(-hue_jitter, hue_jitter)) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hh, rng.uniform(*s), rng.uniform(*v))
    return int(r * 255), int(g * 255), int(b * 255)


def lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``a + (b - a) * t`` (float32, broadcasting), with few temporaries."""
    out = np.subtract(b, a, dtype=F32)
    if out.shape != np.broadcast_shapes(np.shape(a), np.shape(b), np.shape(t)):
        out = out * t
    else:
        out *= t
    out += a
    return out


def base_material(
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
    c = [np.array(cc, F32) for cc in colors]
    n1 = fbm(rng, h, w, max(2.0, scale_m * ppm), 5)
    img = lerp(c[0], c[1], np.clip(0.5 + 0.3 * n1, 0, 1)[..., None])
    if blotch > 0 and len(c) > 2:
        n2 = fbm(rng, h, w, max(2.0, 0.5 * scale_m * ppm), 4)
        thr = 1.4 - 1.6 * blotch
        m = np.clip((n2 - thr) * 6.0, 0, 1)[..., None]
        img = lerp(img, c[2], 0.85 * m)
    if grain > 0:
        img += grain * value_noise(rng, h, w, rng.choice([1, 2]))[..., None]
    return np.clip(img, 0, 255).astype(np.uint8)


# ----------------------------------------------------------------------------------------------------
# drawing helpers (texel units; images are RGB uint8)
# ----------------------------------------------------------------------------------------------------
def ipt(*v: float) -> tuple[int, ...]:
    return tuple(int(round(x)) for x in v)


def contrast_rgb(c: tuple[int, int, int], rng: np.random.Generator) -> tuple[int, int, int]:
    lum = 0.3 * c[0] + 0.59 * c[1] + 0.11 * c[2]
    return random_rgb(rng, (0, 0.6), (0.0, 0.25)) if lum > 120 else random_rgb(rng, (0, 0.4), (0.8, 1.0))


def draw_text(img: np.ndarray, rng: np.random.Generator, x: float, y: float, height: float,
          color: tuple[int, int, int], max_width: float | None = None) -> None:
    """Random text, baseline at ``(x, y)``, capital height about ``height`` texels."""
    if height < 4:
        return
    s = "".join(rng.choice(CHARS, size=int(rng.integers(3, 14)))).strip() or "X"
    font = FONTS[int(rng.integers(len(FONTS)))]
    (_, h1), _ = cv2.getTextSize("H", font, 1.0, 1)
    scale = height / max(h1, 1)
    thick = max(1, int(round(height / rng.uniform(7, 14))))
    if max_width is not None:
        while len(s) > 1 and cv2.getTextSize(s, font, scale, thick)[0][0] > max_width:
            s = s[:-1]
    cv2.putText(img, s, ipt(x, y), font, scale, color, thick, cv2.LINE_AA)


def draw_pixel_art(img: np.ndarray, rng: np.random.Generator, x0: int, y0: int, w: int, h: int) -> None:
    """A blocky random 'photo' (random palette, random block size) in the rectangle."""
    H, W = img.shape[:2]
    x0, y0 = max(0, x0), max(0, y0)
    w, h = min(w, W - x0), min(h, H - y0)
    if w < 4 or h < 4:
        return
    block = int(rng.integers(2, 8))
    gh, gw = max(1, h // block), max(1, w // block)
    k = int(rng.integers(3, 7))
    pal = np.array([random_rgb(rng, (0.1, 1), (0.1, 1)) for _ in range(k)], np.uint8)
    smooth = value_noise(rng, gh, gw, max(1.0, min(gh, gw) / rng.uniform(1.5, 4)))
    idx = np.clip(((smooth - smooth.min()) / (np.ptp(smooth) + 1e-6) * k).astype(int), 0, k - 1)
    flip = rng.random((gh, gw)) < 0.25
    idx[flip] = rng.integers(0, k, size=int(flip.sum()))
    img[y0 : y0 + h, x0 : x0 + w] = cv2.resize(pal[idx], (w, h), interpolation=cv2.INTER_NEAREST)


def draw_poster(img: np.ndarray, rng: np.random.Generator, x0: float, y0: float, w: float, h: float) -> None:
    """A rectangle with random content: text lines, pixel-art photo, circles, polygons."""
    x0, y0, w, h = ipt(x0, y0, w, h)
    if w < 6 or h < 6:
        return
    bg = random_rgb(rng, (0.0, 0.9), (0.25, 1.0))
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), bg, -1)
    fg = contrast_rgb(bg, rng)
    for _ in range(int(rng.integers(2, 9))):
        kind = rng.random()
        cx, cy = x0 + rng.uniform(0.05, 0.8) * w, y0 + rng.uniform(0.1, 0.9) * h
        if kind < 0.35:
            draw_text(img, rng, cx, cy, rng.uniform(0.06, 0.2) * h, fg if rng.random() < 0.6 else random_rgb(rng), x0 + w - cx)
        elif kind < 0.55:
            pw, ph = rng.uniform(0.2, 0.6) * w, rng.uniform(0.2, 0.6) * h
            draw_pixel_art(img, rng, *ipt(cx - pw / 2, cy - ph / 2, pw, ph))
        elif kind < 0.75:
            r = rng.uniform(0.04, 0.2) * min(w, h)
            cv2.circle(img, ipt(cx, cy), int(r), random_rgb(rng), -1 if rng.random() < 0.6 else 2, cv2.LINE_AA)
        else:
            pts = np.stack([cx + rng.uniform(-0.2, 0.2, 5) * w, cy + rng.uniform(-0.2, 0.2, 5) * h], 1)
            cv2.fillPoly(img, [pts.astype(np.int32)], random_rgb(rng), cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), random_rgb(rng, (0, 0.4), (0.05, 0.5)), int(rng.integers(1, 4)))


def draw_bookshelf(img: np.ndarray, rng: np.random.Generator, x0: float, y0: float, w: float, h: float, ppm: float) -> None:
    """Shelves of books with random widths, heights and colours."""
    x0, y0, w, h = ipt(x0, y0, w, h)
    board = random_rgb(rng, (0.2, 0.6), (0.2, 0.6))
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
            col = random_rgb(rng, (0.2, 0.9), (0.15, 0.95))
            cv2.rectangle(img, ipt(x, ybot - bh), ipt(min(x + bw, x0 + w - 2), ybot - 2), col, -1)
            if bw > 5 and rng.random() < 0.5:
                cv2.line(img, ipt(x + 1, ybot - bh * rng.uniform(0.3, 0.8)), ipt(x + bw - 1, ybot - bh * rng.uniform(0.3, 0.8)),
                         contrast_rgb(col, rng), 1)
            x += bw + rng.uniform(0, 1.5)
        cv2.rectangle(img, ipt(x0, ybot - 2), ipt(x0 + w, ybot + 1), board, -1)
    cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), board, 3)


def random_rgbs(rng: np.random.Generator, n: int, s: tuple[float, float] = (0.2, 0.8), v: tuple[float, float] = (0.3, 0.9),
               hue: float | None = None, hue_jitter: float = 1.0) -> np.ndarray:
    """``n`` random colours ``(n, 3)`` int (RGB 0..255), vectorised :func:`random_rgb`."""
    hh = rng.random(n) if hue is None else np.mod(hue + rng.uniform(-hue_jitter, hue_jitter, n), 1.0)
    ss, vv = rng.uniform(*s, n), rng.uniform(*v, n)
    i = np.floor(hh * 6).astype(int) % 6
    f = hh * 6 - np.floor(hh * 6)
    p, q, t = vv * (1 - ss), vv * (1 - ss * f), vv * (1 - ss * (1 - f))
    table = np.stack([np.stack(c, 1) for c in ((vv, t, p), (q, vv, p), (p, vv, t), (p, q, vv), (t, p, vv), (vv, p, q))], 0)
    return (table[i, np.arange(n)] * 255).astype(int)


def scatter_shapes(img: np.ndarray, rng: np.random.Generator, count: int, size: tuple[float, float],
                    color: tuple = (), outline: float = 0.5) -> None:
    """``count`` random small filled polygons / ellipses (stones, stains, clutter); ``color`` holds the
    HSV ranges of :func:`random_rgb` (s, v, hue, hue_jitter)."""
    H, W = img.shape[:2]
    if count <= 0:
        return
    cols = random_rgbs(rng, count, *color).tolist()
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


def wrap_draw(img: np.ndarray, draw: Callable[[np.ndarray], None], margin: int) -> None:
    """Draw on a tileable texture without seams: ``draw`` paints on the texture padded (wrap) by
    ``margin`` texels on each side; every changed texel is then folded back to its periodic position."""
    H, W = img.shape[:2]
    m = int(margin)
    canvas = np.pad(img, ((m, m), (m, m), (0, 0)), mode="wrap")
    ref = canvas.copy()
    draw(canvas)
    ys, xs = np.nonzero(np.any(canvas != ref, axis=2))
    img[(ys - m) % H, (xs - m) % W] = canvas[ys, xs]

