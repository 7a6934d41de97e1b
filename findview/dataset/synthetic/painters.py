"""Surface painters: one metric-scaled texture per scene surface (walls, floors, ceilings, furniture,
rocks, facades, roofs, tileable ground, clouds).

Each painter takes the texture size in texels and ``ppm`` (texels per metre), so objects keep their
real-world size whatever the resolution, and returns an RGB ``uint8`` image ``(h, w, 3)`` (clouds: a
float32 alpha ``(size, size)``). Row 0 of a wall texture is at the ceiling, the last row at the floor.
"""

from __future__ import annotations

import numpy as np
import cv2

from findview.dataset.synthetic.textures import (
    F32,
    base_material,
    contrast_rgb,
    draw_bookshelf,
    draw_poster,
    draw_text,
    fbm,
    ipt,
    lerp,
    random_rgb,
    scatter_shapes,
    value_noise,
    wrap_draw,
)

__all__ = [
    "Style", "paint_wall", "paint_floor", "paint_ceiling", "paint_furniture", "paint_rock", "paint_facade",
    "paint_roof", "paint_ground", "paint_clouds",
]


class Style:
    """Per-scene palette."""

    def __init__(self, rng: np.random.Generator, outdoor: bool) -> None:
        self.hue = rng.random()
        self.wall = [random_rgb(rng, (0.05, 0.45), (0.55, 0.95), self.hue, 0.08) for _ in range(3)]
        self.floor = [random_rgb(rng, (0.3, 0.8), (0.25, 0.75), rng.random(), 0.05) for _ in range(3)]
        self.ceiling = [random_rgb(rng, (0.0, 0.15), (0.75, 0.98)) for _ in range(3)]
        self.accent = [random_rgb(rng, (0.4, 1.0), (0.4, 1.0)) for _ in range(4)]
        self.outdoor = outdoor


def paint_wall(rng: np.random.Generator, st: Style, w: int, h: int, ppm: float, big: bool) -> np.ndarray:
    wall_colors = [st.wall[0], st.wall[1], st.wall[2] if rng.random() < 0.5 else st.accent[int(rng.integers(4))]]
    img = base_material(rng, h, w, ppm, wall_colors, scale_m=rng.uniform(0.3, 1.0), blotch=rng.uniform(0.2, 0.6))
    W_m, H_m = w / ppm, h / ppm
    floor_y = h  # texel row of the floor (v = 0 at the ceiling)
    # skirting board
    sk = int(rng.uniform(0.06, 0.14) * ppm)
    cv2.rectangle(img, (0, floor_y - sk), (w, floor_y), random_rgb(rng, (0, 0.5), (0.1, 0.8)), -1)
    # windows / doors
    for _ in range(int(rng.integers(0, 3))):
        ww, wh = rng.uniform(0.6, 1.8) * ppm, rng.uniform(0.8, 1.5) * ppm
        x, y = rng.uniform(0, max(1, w - ww)), floor_y - rng.uniform(0.9, 1.1) * ppm - wh
        sky = np.array(random_rgb(rng, (0.2, 0.6), (0.7, 1.0), 0.58, 0.05), F32)
        x0, y0, x1, y1 = ipt(x, y, x + ww, y + wh)
        y0 = max(0, y0)
        if x1 - x0 > 8 and y1 - y0 > 8:
            grad = np.linspace(1.0, 0.75, y1 - y0, dtype=F32)[:, None, None] * sky
            img[y0:y1, x0:x1] = np.clip(grad, 0, 255).astype(np.uint8)
            scatter_shapes(img[y0:y1, x0:x1], rng, int(rng.integers(3, 9)), (3, (y1 - y0) / 4),
                            ((0.2, 0.7), (0.2, 0.7),))
            frame = random_rgb(rng, (0, 0.2), (0.3, 1.0))
            cv2.rectangle(img, (x0, y0), (x1, y1), frame, max(2, int(0.04 * ppm)))
            cv2.line(img, ((x0 + x1) // 2, y0), ((x0 + x1) // 2, y1), frame, max(1, int(0.02 * ppm)))
    if rng.random() < 0.7:
        dw, dh = rng.uniform(0.8, 1.0) * ppm, rng.uniform(2.0, 2.2) * ppm
        x = rng.uniform(0, max(1, w - dw))
        col = random_rgb(rng, (0.1, 0.7), (0.2, 0.8))
        cv2.rectangle(img, ipt(x, floor_y - dh), ipt(x + dw, floor_y), col, -1)
        cv2.rectangle(img, ipt(x, floor_y - dh), ipt(x + dw, floor_y), contrast_rgb(col, rng), max(2, int(0.03 * ppm)))
        cv2.circle(img, ipt(x + 0.85 * dw, floor_y - 1.0 * ppm), max(2, int(0.03 * ppm)), (220, 200, 120), -1)
        if rng.random() < 0.5:
            draw_poster(img, rng, x + 0.2 * dw, floor_y - 0.8 * dh, 0.6 * dw, 0.2 * dh)
    # bookshelves
    for _ in range(int(rng.integers(0, 3 if big else 2))):
        bw, bh = rng.uniform(0.8, 2.5) * ppm, rng.uniform(1.0, 2.0) * ppm
        x = rng.uniform(0, max(1, w - bw))
        draw_bookshelf(img, rng, x, floor_y - bh - rng.uniform(0, 0.3) * ppm, bw, bh, ppm)
    # posters, pictures, notes
    n_post = int(rng.poisson(W_m * H_m * rng.uniform(0.5, 1.0))) + 2
    for _ in range(n_post):
        pw, ph = rng.uniform(0.2, 1.0) * ppm, rng.uniform(0.2, 1.0) * ppm
        x, y = rng.uniform(-0.1 * pw, max(-0.1 * pw, w - 0.9 * pw)), floor_y - rng.uniform(0.8, max(1.0, H_m - 0.3)) * ppm - ph / 2
        draw_poster(img, rng, x, y, pw, ph)
    for _ in range(int(rng.poisson(W_m * H_m * 1.5))):
        x, y = rng.uniform(0, w), rng.uniform(0.1 * h, h - sk)
        draw_text(img, rng, x, y, rng.uniform(0.03, 0.12) * ppm, random_rgb(rng, (0, 1), (0, 0.6)), None)
    # switches / outlets
    for _ in range(int(rng.integers(1, 5))):
        x, y = rng.uniform(0, w), floor_y - rng.choice([0.3, 1.1]) * ppm
        s = 0.08 * ppm
        cv2.rectangle(img, ipt(x, y), ipt(x + s, y + s * 1.4), (235, 235, 230), -1)
        cv2.rectangle(img, ipt(x, y), ipt(x + s, y + s * 1.4), (90, 90, 90), 1)
    return img


def paint_floor(rng: np.random.Generator, st: Style, w: int, h: int, ppm: float) -> np.ndarray:
    img = base_material(rng, h, w, ppm, st.floor, scale_m=1.0, blotch=0.3, grain=6)
    if rng.random() < 0.55:  # planks: rows of random width, random lengths and tints
        y = 0.0
        while y < h:
            ph = rng.uniform(0.1, 0.25) * ppm
            x = -rng.uniform(0, 1.5) * ppm
            while x < w:
                pl = rng.uniform(0.6, 2.2) * ppm
                tint = np.array(st.floor[int(rng.integers(3))], F32) * rng.uniform(0.75, 1.2)
                x0, y0, x1, y1 = ipt(max(0, x), y, min(w, x + pl), min(h, y + ph))
                if x1 > x0 and y1 > y0:
                    reg = img[y0:y1, x0:x1].astype(F32)
                    img[y0:y1, x0:x1] = np.clip(reg * 0.5 + tint * 0.5, 0, 255).astype(np.uint8)
                    cv2.rectangle(img, (x0, y0), (x1, y1), tuple(int(c * 0.35) for c in st.floor[0]), 1)
                x += pl
            y += ph
        grain = value_noise(rng, h, max(1, w // 8), 2)
        grain = cv2.resize(grain, (w, h), interpolation=cv2.INTER_LINEAR)
        img = np.clip(img.astype(F32) + 14 * grain[..., None], 0, 255).astype(np.uint8)
    else:  # tiles with per-tile colours
        ts = rng.uniform(0.3, 0.6) * ppm
        grout = random_rgb(rng, (0, 0.2), (0.2, 0.8))
        for ty in range(int(h / ts) + 1):
            for tx in range(int(w / ts) + 1):
                col = np.array(st.floor[int(rng.integers(3))], F32) * rng.uniform(0.8, 1.15)
                x0, y0, x1, y1 = ipt(tx * ts, ty * ts, (tx + 1) * ts, (ty + 1) * ts)
                reg = img[y0:y1, x0:x1].astype(F32)
                if reg.size:
                    img[y0:y1, x0:x1] = np.clip(reg * 0.45 + col * 0.55, 0, 255).astype(np.uint8)
                    cv2.rectangle(img, (x0, y0), (x1, y1), grout, max(1, int(0.01 * ppm)))
    # rugs
    for _ in range(int(rng.integers(0, 3))):
        rw, rh = rng.uniform(1.0, 3.0) * ppm, rng.uniform(0.8, 2.0) * ppm
        x, y = rng.uniform(0, max(1, w - rw)), rng.uniform(0, max(1, h - rh))
        x0, y0, x1, y1 = ipt(x, y, x + rw, y + rh)
        col = random_rgb(rng, (0.3, 0.9), (0.2, 0.8))
        cv2.rectangle(img, (x0, y0), (x1, y1), col, -1)
        for b in range(int(rng.integers(1, 4))):
            inset = int((b + 1) * rng.uniform(0.04, 0.1) * ppm)
            cv2.rectangle(img, (x0 + inset, y0 + inset), (x1 - inset, y1 - inset), random_rgb(rng), max(1, int(0.02 * ppm)))
        scatter_shapes(img[y0:y1, x0:x1], rng, int(rng.integers(5, 25)), (0.03 * ppm, 0.15 * ppm), ())
    # clutter: papers, stains
    scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 1.5)), (0.02 * ppm, 0.12 * ppm),
                    ((0, 0.8), (0.1, 0.9),))
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.4))):
        draw_poster(img, rng, rng.uniform(0, w), rng.uniform(0, h), rng.uniform(0.15, 0.4) * ppm, rng.uniform(0.15, 0.4) * ppm)
    return img


def paint_ceiling(rng: np.random.Generator, st: Style, w: int, h: int, ppm: float) -> np.ndarray:
    img = base_material(rng, h, w, ppm, st.ceiling, scale_m=0.8, blotch=0.35, grain=6)
    ps = rng.uniform(0.5, 0.7) * ppm
    line = random_rgb(rng, (0, 0.2), (0.3, 0.6))
    y = rng.uniform(0, ps)
    while y < h:  # panels with per-panel shade and jittered seams
        x = rng.uniform(0, ps)
        while x < w:
            pw = ps * rng.uniform(0.8, 1.3)
            x0, y0, x1, y1 = ipt(x, y, x + pw, y + ps)
            reg = img[max(0, y0):y1, max(0, x0):x1]
            if reg.size:
                reg[:] = np.clip(reg.astype(F32) * rng.uniform(0.82, 1.08), 0, 255).astype(np.uint8)
            cv2.rectangle(img, (x0, y0), (x1, y1), line, 1)
            x += pw
        y += ps
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.25)) + 2):  # lamps
        lx, ly = rng.uniform(0, w), rng.uniform(0, h)
        if rng.random() < 0.5:
            r = rng.uniform(0.1, 0.25) * ppm
            cv2.circle(img, ipt(lx, ly), int(r * 1.3), (90, 90, 90), -1, cv2.LINE_AA)
            cv2.circle(img, ipt(lx, ly), int(r), (255, 250, 225), -1, cv2.LINE_AA)
        else:
            lw, lh = rng.uniform(0.4, 1.2) * ppm, rng.uniform(0.1, 0.3) * ppm
            cv2.rectangle(img, ipt(lx, ly), ipt(lx + lw, ly + lh), (80, 80, 85), -1)
            cv2.rectangle(img, ipt(lx + 3, ly + 3), ipt(lx + lw - 3, ly + lh - 3), (250, 250, 235), -1)
    for _ in range(int(rng.poisson(w * h / ppm**2 * 0.3)) + 1):  # vents
        vx, vy = rng.uniform(0, w), rng.uniform(0, h)
        vw, vh = rng.uniform(0.2, 0.5) * ppm, rng.uniform(0.15, 0.4) * ppm
        cv2.rectangle(img, ipt(vx, vy), ipt(vx + vw, vy + vh), (200, 200, 200), -1)
        for k in range(1, int(vh / 4)):
            cv2.line(img, ipt(vx + 2, vy + 4 * k), ipt(vx + vw - 2, vy + 4 * k), (70, 70, 70), 1)
    scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.8)), (0.02 * ppm, 0.1 * ppm),
                    ((0, 0.5), (0.2, 0.9),))
    return img


def paint_furniture(rng: np.random.Generator, st: Style, w: int, h: int, ppm: float, top: bool) -> np.ndarray:
    base = [random_rgb(rng, (0.2, 0.8), (0.2, 0.85)) for _ in range(2)] + [st.accent[int(rng.integers(4))]]
    img = base_material(rng, h, w, ppm, base, scale_m=rng.uniform(0.2, 0.6), blotch=rng.uniform(0.1, 0.5))
    if top:
        for _ in range(int(rng.poisson(w * h / ppm**2 * 6)) + 1):
            pw, ph = rng.uniform(0.1, 0.5) * ppm, rng.uniform(0.1, 0.4) * ppm
            draw_poster(img, rng, rng.uniform(-pw / 2, w), rng.uniform(-ph / 2, h), pw, ph)
        scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 8)) + 2, (0.03 * ppm, 0.1 * ppm), ())
        return img
    # drawers / doors with handles, random grid
    rows, cols = int(rng.integers(1, 5)), int(rng.integers(1, 4))
    dw, dh = w / cols, h / rows
    edge = contrast_rgb(base[0], rng)
    for r in range(rows):
        for c in range(cols):
            if rng.random() < 0.25:
                continue
            x0, y0 = c * dw + 3, r * dh + 3
            cv2.rectangle(img, ipt(x0, y0), ipt(x0 + dw - 6, y0 + dh - 6), edge, max(1, int(0.01 * ppm)))
            hx, hy = x0 + dw * rng.uniform(0.3, 0.7), y0 + dh * rng.uniform(0.2, 0.5)
            cv2.rectangle(img, ipt(hx - 0.05 * ppm, hy), ipt(hx + 0.05 * ppm, hy + 0.015 * ppm + 2), (60, 60, 60), -1)
    for _ in range(int(rng.integers(0, 4))):
        draw_poster(img, rng, rng.uniform(0, w * 0.8), rng.uniform(0, h * 0.8), rng.uniform(0.08, 0.3) * ppm, rng.uniform(0.05, 0.2) * ppm)
    return img


def paint_rock(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    g = rng.uniform(90, 170)
    cols = [random_rgb(rng, (0, 0.2), (g / 255 * 0.8, g / 255)), random_rgb(rng, (0, 0.25), (0.3, 0.75)), random_rgb(rng, (0.3, 0.7), (0.3, 0.6), 0.25, 0.1)]
    img = base_material(rng, h, w, ppm, cols, scale_m=rng.uniform(0.3, 1.0), blotch=0.5, grain=14)
    for _ in range(int(rng.integers(3, 12))):  # cracks
        pts = [np.array([rng.uniform(0, w), rng.uniform(0, h)])]
        for _ in range(int(rng.integers(3, 9))):
            pts.append(pts[-1] + rng.normal(0, 0.15 * ppm, 2))
        cv2.polylines(img, [np.array(pts, np.int32)], False, (35, 35, 35), max(1, int(rng.integers(1, 3))), cv2.LINE_AA)
    scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 6)) + 3, (0.02 * ppm, 0.12 * ppm),
                    ((0.2, 0.6), (0.3, 0.8), 0.2, 0.12))
    return img


def paint_facade(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    cols = [random_rgb(rng, (0.05, 0.5), (0.45, 0.95)) for _ in range(2)] + [random_rgb(rng, (0.1, 0.6), (0.2, 0.7))]
    img = base_material(rng, h, w, ppm, cols, scale_m=rng.uniform(0.5, 2.0), blotch=rng.uniform(0.2, 0.6), grain=12)
    storey = rng.uniform(2.8, 3.6) * ppm
    n_floors = max(1, int(h / storey))
    frame = random_rgb(rng, (0, 0.3), (0.1, 0.95))
    for f in range(n_floors):
        ybase = h - f * storey
        x = rng.uniform(0.3, 1.5) * ppm
        while x < w - 0.8 * ppm:
            ww, wh = rng.uniform(0.6, 1.6) * ppm, rng.uniform(0.9, 1.6) * ppm
            y0 = ybase - storey * 0.35 - wh
            if f == 0 and rng.random() < 0.25:  # a door
                dw, dh = rng.uniform(0.9, 1.4) * ppm, rng.uniform(2.0, 2.4) * ppm
                col = random_rgb(rng, (0.2, 0.8), (0.15, 0.7))
                cv2.rectangle(img, ipt(x, ybase - dh), ipt(x + dw, ybase), col, -1)
                cv2.rectangle(img, ipt(x, ybase - dh), ipt(x + dw, ybase), frame, max(1, int(0.06 * ppm)))
                if rng.random() < 0.6:
                    draw_poster(img, rng, x - 0.2 * ppm, ybase - dh - 0.6 * ppm, dw + 0.4 * ppm, 0.45 * ppm)
                x += dw + rng.uniform(0.5, 2.0) * ppm
                continue
            glass = random_rgb(rng, (0.1, 0.6), (0.1, 0.95), 0.6 if rng.random() < 0.6 else 0.12, 0.06)
            cv2.rectangle(img, ipt(x, y0), ipt(x + ww, y0 + wh), glass, -1)
            if rng.random() < 0.5:  # curtain
                cv2.rectangle(img, ipt(x, y0), ipt(x + ww * rng.uniform(0.2, 0.6), y0 + wh), random_rgb(rng), -1)
            cv2.rectangle(img, ipt(x, y0), ipt(x + ww, y0 + wh), frame, max(1, int(0.08 * ppm)))
            if rng.random() < 0.6:
                cv2.line(img, ipt(x + ww / 2, y0), ipt(x + ww / 2, y0 + wh), frame, max(1, int(0.05 * ppm)))
            cv2.rectangle(img, ipt(x - 2, y0 + wh), ipt(x + ww + 2, y0 + wh + 0.06 * ppm), (200, 200, 195), -1)
            x += ww + rng.uniform(0.5, 2.5) * ppm
    for _ in range(int(rng.integers(0, 4))):  # signs
        sw, sh = rng.uniform(0.8, 3.0) * ppm, rng.uniform(0.3, 0.8) * ppm
        x, y = rng.uniform(0, max(1, w - sw)), rng.uniform(0.2 * h, max(0.2 * h, h - 2.5 * ppm))
        bg = random_rgb(rng, (0.3, 1), (0.3, 1))
        cv2.rectangle(img, ipt(x, y), ipt(x + sw, y + sh), bg, -1)
        draw_text(img, rng, x + 0.05 * sw, y + 0.75 * sh, 0.5 * sh, contrast_rgb(bg, rng), 0.9 * sw)
    scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.3)) + 2, (0.1 * ppm, 0.5 * ppm),
                    ((0.3, 1), (0.2, 0.9),))
    return img


def paint_roof(rng: np.random.Generator, w: int, h: int, ppm: float) -> np.ndarray:
    cols = [random_rgb(rng, (0.1, 0.5), (0.15, 0.45)) for _ in range(3)]
    img = base_material(rng, h, w, ppm, cols, scale_m=1.0, blotch=0.5, grain=16)
    scatter_shapes(img, rng, int(rng.poisson(w * h / ppm**2 * 0.3)) + 2, (0.2 * ppm, 0.8 * ppm),
                    ((0, 0.3), (0.3, 0.9),))
    return img


def paint_ground(rng: np.random.Generator, size: int, ppm: float) -> np.ndarray:
    """Tileable ground (grass, dirt patches, stones, flowers, a path) ``(size, size, 3)`` uint8."""
    hue = rng.uniform(0.17, 0.33)
    grass = [np.array(random_rgb(rng, (0.35, 0.8), (0.25, 0.6), hue, 0.04), F32) for _ in range(3)]
    dirt = np.array(random_rgb(rng, (0.3, 0.6), (0.3, 0.6), 0.08, 0.03), F32)
    half = size // 2  # the smooth colour fields are composed at half resolution, then upsampled
    n1 = fbm(rng, half, half, 128, 6, 0.6, wrap=True)
    n2 = fbm(rng, half, half, 64, 4, 0.6, wrap=True)
    n3 = fbm(rng, half, half, 256, 4, 0.5, wrap=True)
    low = lerp(grass[0], grass[1], np.clip(0.5 + 0.35 * n1, 0, 1)[..., None])
    low = lerp(low, grass[2], np.clip((n2 - 0.3) * 3, 0, 1)[..., None] * 0.8)
    low = lerp(low, dirt, np.clip((n3 - rng.uniform(0.3, 1.0)) * 2.5, 0, 1)[..., None])
    low = np.pad(low, ((1, 1), (1, 1), (0, 0)), mode="wrap")
    img = cv2.resize(low, ((half + 2) * 2, (half + 2) * 2), interpolation=cv2.INTER_LINEAR)[2 : 2 + size, 2 : 2 + size]
    img += 22 * rng.standard_normal((size, size, 1), dtype=F32)
    img = np.clip(img, 0, 255).astype(np.uint8)

    def draw(canvas: np.ndarray) -> None:
        ch, cw = canvas.shape[:2]
        pts = [np.array([rng.uniform(0, cw), rng.uniform(0, ch)])]
        for _ in range(60):  # a winding path
            pts.append(pts[-1] + rng.normal(0, 0.8 * ppm, 2))
        cv2.polylines(canvas, [np.array(pts).astype(np.int32)], False, tuple(int(c) for c in dirt * 1.1),
                      int(rng.uniform(0.6, 1.2) * ppm), cv2.LINE_AA)
        n = int(ch * cw / ppm**2 * 1.2)
        scatter_shapes(canvas, rng, n, (0.02 * ppm, 0.15 * ppm), ((0, 0.2), (0.3, 0.85),), outline=0.8)
        scatter_shapes(canvas, rng, n, (0.01 * ppm, 0.03 * ppm), ((0.5, 1.0), (0.7, 1.0),))
        scatter_shapes(canvas, rng, n // 2, (0.03 * ppm, 0.08 * ppm), ((0.5, 0.9), (0.15, 0.45), hue, 0.06))

    wrap_draw(img, draw, margin=int(ppm))
    return img


def paint_clouds(rng: np.random.Generator, size: int, coverage: float) -> np.ndarray:
    """Tileable cloud alpha ``(size, size)`` float32 in [0, 1]."""
    n = fbm(rng, size, size, size // 4, 8, 0.58, wrap=True)
    thr = 1.2 - 2.0 * coverage
    return np.clip((n - thr) * 1.3, 0, 1).astype(F32)

