"""Scene layouts: the four scene kinds (``room``, ``hall``, ``landscape``, ``village``) built from
textured boxes and planes around the camera, and :func:`generate_panorama`.

Distances are metres, the camera at the origin at eye height above the floor / ground. The texture
resolution of each surface (:func:`ppm_for`) follows its distance so that a texel is about 0.8
panorama pixels.
"""

from __future__ import annotations

import math
from typing import Callable

import cv2
import numpy as np

from findview.dataset.synthetic.caster import Caster, Surface
from findview.dataset.synthetic.painters import (
    Style,
    paint_ceiling,
    paint_clouds,
    paint_facade,
    paint_floor,
    paint_furniture,
    paint_ground,
    paint_rock,
    paint_roof,
    paint_wall,
)
from findview.dataset.synthetic.textures import F32, draw_bookshelf, fbm, lerp, random_rgb

__all__ = ["SCENE_KINDS", "generate_panorama", "ppm_for", "tex_size", "place_boxes", "box_faces"]

SCENE_KINDS = ("room", "hall", "landscape", "village")


def ppm_for(distance: float, height: int, lo: float = 12.0, hi: float = 100.0) -> float:
    """Texels per metre so that a texel is about 0.8 panorama pixels at ``distance`` metres."""
    return float(np.clip(1.0 / (0.8 * max(distance, 0.05) * math.pi / height), lo, hi))


def tex_size(size_m: float, ppm: float) -> int:
    return max(8, int(math.ceil(size_m * ppm)))


def place_boxes(rng: np.random.Generator, n: int, bounds: tuple[float, float, float, float],
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


def box_faces(caster: Caster, lo: list[float], hi: list[float], H: int, paint: Callable[[int, int, float, bool], np.ndarray],
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
        ppm = ppm_for(dist, H)
        tex = paint(tex_size(su, ppm), tex_size(sv, ppm), ppm, a == 1)
        sids[a] = caster.add_surface(Surface(tex, ppm, (su, sv), shades[a], ao, fog))
    return sids


def indoor_scene(rng: np.random.Generator, width: int, big: bool) -> np.ndarray:
    """A ``room`` (``big=False``) or ``hall``: a textured box around the eye with furniture boxes;
    ``(width // 2, width, 3)`` RGB uint8."""
    st = Style(rng, outdoor=False)
    caster = Caster(width)
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
        ppm = ppm_for(dist, H, hi=90)
        tex = paint_wall(rng, st, tex_size(wm, ppm), tex_size(height, ppm), ppm, big)
        sids[name] = caster.add_surface(Surface(tex, ppm, (wm, height), rng.uniform(0.82, 1.0), 0.35))
    ppm = ppm_for(eye, H, hi=90)
    sids["floor"] = caster.add_surface(
        Surface(paint_floor(rng, st, tex_size(x1 - x0, ppm), tex_size(z1 - z0, ppm), ppm), ppm, (x1 - x0, z1 - z0), 0.9, 0.4)
    )
    ppm = ppm_for(y1, H, hi=90)
    sids["ceiling"] = caster.add_surface(
        Surface(paint_ceiling(rng, st, tex_size(x1 - x0, ppm), tex_size(z1 - z0, ppm), ppm), ppm, (x1 - x0, z1 - z0), 0.95, 0.4)
    )
    caster.room(lo, hi, sids)
    n = int(rng.integers(6, 13)) if big else int(rng.integers(3, 7))
    boxes = place_boxes(rng, n, (x0 + 0.05, x1 - 0.05, z0 + 0.05, z1 - 0.05),
                         (0.4, 3.0 if big else 1.8), (0.4, min(2.4, height - 0.2)), 0.7, wall_snap=0.5)
    for (bx0, bz0), (bx1, bz1), bh in boxes:
        blo, bhi = [bx0, y0, bz0], [bx1, y0 + bh, bz1]

        def paint(w: int, h: int, ppm: float, top: bool) -> np.ndarray:
            if not top and rng.random() < 0.3 and h > 0.8 * ppm:
                img = paint_furniture(rng, st, w, h, ppm, False)
                draw_bookshelf(img, rng, 0, 0, w, h, ppm)
                return img
            return paint_furniture(rng, st, w, h, ppm, top)

        fs = box_faces(caster, blo, bhi, H, paint, (rng.uniform(0.7, 0.9), 1.0, rng.uniform(0.75, 0.95)), 0.25, math.inf)
        caster.box(blo, bhi, fs)
    col, hit = caster.shade()
    return np.clip(col, 0, 255).astype(np.uint8).reshape(H, width, 3)


def _add_clouds(rng: np.random.Generator, sky: np.ndarray, d: tuple[np.ndarray, ...], lat: np.ndarray, W: int,
                H: int) -> None:
    """Clouds on a plane 1.5 km up (8 m per texel, tileable, 5 mip levels), faded out near the horizon,
    blended into ``sky`` ((rows * W, 3) float RGB of the rows at or above the horizon) in place."""
    dx, dy, dz = d
    csize, cm = 1024, 8.0
    alpha_tex = paint_clouds(rng, csize, rng.uniform(0.25, 0.65))
    shade_tex = 0.78 + 0.22 * np.clip(0.5 + 0.3 * fbm(rng, csize, csize, 64, 5, wrap=True), 0, 1)
    mip = np.stack([alpha_tex, shade_tex.astype(F32)], -1)
    rc = int(np.count_nonzero(lat > 1.0))  # rows that can show clouds
    if rc > 0:
        up = np.maximum(dy[: rc * W], 0.01)
        tc = 1500.0 / up
        cx = (tc * dx[: rc * W] / cm).reshape(rc, W)
        cz = (tc * dz[: rc * W] / cm).reshape(rc, W)
        lvl = np.clip(np.log2(np.maximum(tc * (np.pi / H) / cm, 1e-6)), 0, 4).reshape(rc, W)
        c_acc = np.zeros((rc, W, 2), F32)
        for k in range(5):
            sc = 2.0**k
            wgt = np.clip(1 - np.abs(lvl - k), 0, 1)
            if wgt.any():
                mx = np.mod(cx / sc, mip.shape[1]).astype(F32)
                mz = np.mod(cz / sc, mip.shape[0]).astype(F32)
                c_acc += cv2.remap(mip, mx, mz, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP) * wgt[..., None]
            mip = cv2.pyrDown(np.pad(mip, ((2, 2), (2, 2), (0, 0)), mode="wrap"))[1:-1, 1:-1]
        alpha = (c_acc[..., 0] * np.clip((lat[:rc, None] - 1.0) / 10.0, 0, 1)).reshape(-1, 1)
        cloud_col = np.array([252, 252, 250], F32) * c_acc[..., 1].reshape(-1, 1)
        sky[: rc * W] = sky[: rc * W] * (1 - alpha) + cloud_col * alpha


def _add_mountains(rng: np.random.Generator, bg: np.ndarray, lat: np.ndarray, nb: int, W: int, haze: np.ndarray) -> None:
    """3 ridgelines (far to near) at infinity, snow-capped and hazy, painted into ``bg`` ((nb, W, 3) float RGB of
    the rows at or above the horizon; ``lat`` their latitudes, degrees) on the band just above the horizon."""
    layer_col = [np.array(random_rgb(rng, (0.1, 0.5), (0.25, 0.6), rng.uniform(0.2, 0.6), 0.1), F32) for _ in range(3)]
    elevs = []
    for k in range(3):
        cell = max(1, W // 8)
        prof = fbm(rng, cell, W, cell, 7, 0.55, wrap=True)[0]
        ridge = 1 - np.abs(prof) / (np.abs(prof).max() + 1e-6)
        elevs.append((rng.uniform(1.5, 4) + rng.uniform(6, 22 - 5 * k) * ridge**1.5).astype(F32))
    r0 = int(np.count_nonzero(lat > max(float(e.max()) for e in elevs) + 0.5))
    band = bg[r0:nb]
    bh = nb - r0
    if bh > 0:
        rock = fbm(rng, bh, W, max(2, W // 256), 6, 0.6, wrap=True)
        detail = rng.standard_normal((bh, W), dtype=F32)
        lat2 = lat[r0:nb, None]
        for k in range(3):
            elev = elevs[k][None, :]
            mask = lat2 < elev
            c = layer_col[k] * (0.7 + 0.16 * rock + 0.1 * detail)[..., None]
            snowline = float(elevs[k].max()) * rng.uniform(0.55, 0.9)
            if k < 2:
                snow = lat2 > snowline + 1.5 * rock
                c = np.where(snow[..., None], np.array([240, 240, 245], F32) * (0.85 + 0.08 * rock[..., None]), c)
            h_fog = ((0.65 - 0.25 * k) + 0.25 * np.clip(1 - lat2 / np.maximum(elev, 1e-3), 0, 1))[..., None]
            c = c * (1 - h_fog) + haze * h_fog
            band = np.where(mask[..., None], c, band)
        bg[r0:nb] = band


def outdoor_scene(rng: np.random.Generator, width: int, village: bool) -> np.ndarray:
    """A ``landscape`` (``village=False``) or ``village``: ground plane, rocks (and houses, crates), sky,
    sun, clouds and mountain ridges; ``(width // 2, width, 3)`` RGB uint8."""
    caster = Caster(width)
    H, W = caster.H, width
    eye = rng.uniform(1.5, 1.8)
    sun_az, sun_el = rng.uniform(-np.pi, np.pi), rng.uniform(np.radians(20), np.radians(60))
    sun = np.array([np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el), np.cos(sun_el) * np.cos(sun_az)])
    haze = np.array(random_rgb(rng, (0.05, 0.25), (0.75, 0.95), 0.58, 0.05), F32)
    fog = rng.uniform(120, 400)
    # ground: a tileable 32 m texture
    gsize, gppm = 1536, 48.0
    ground = caster.add_surface(Surface(paint_ground(rng, gsize, gppm), gppm, (math.inf, math.inf), 1.0, 0.0, fog, wrap=True))
    caster.plane_y(-eye, ground, (rng.uniform(0, 32), rng.uniform(0, 32)))

    def face_shade(a: int, lo: list[float], hi: list[float]) -> float:
        n = np.zeros(3)
        n[a] = -1.0 if lo[a] > 0 else 1.0
        return float(0.55 + 0.45 * max(0.0, float(n @ sun)))

    objects = []
    if village:
        objects += [("house", b) for b in place_boxes(rng, int(rng.integers(6, 14)), (-60, 60, -60, 60), (5, 14), (3, 13), 7)]
        objects += [("crate", b) for b in place_boxes(rng, int(rng.integers(4, 10)), (-25, 25, -25, 25), (0.6, 4), (0.5, 2.2), 2.5)]
    objects += [("rock", b) for b in place_boxes(rng, int(rng.integers(6, 16)), (-40, 40, -40, 40), (0.4, 4), (0.3, 2.5), 2.0)]
    if rng.random() < 0.7:  # a stone wall
        objects += [("rock", b) for b in place_boxes(rng, 1, (-30, 30, -30, 30), (6, 20), (0.6, 1.4), 3.0)]
    for kind, ((bx0, bz0), (bx1, bz1), bh) in objects:
        blo, bhi = [bx0, -eye, bz0], [bx1, -eye + bh, bz1]

        def paint(w: int, h: int, ppm: float, top: bool, kind: str = kind) -> np.ndarray:
            if kind == "house":
                return paint_roof(rng, w, h, ppm) if top else paint_facade(rng, w, h, ppm)
            if kind == "crate":
                return paint_furniture(rng, Style(rng, True), w, h, ppm, top)
            return paint_rock(rng, w, h, ppm)

        shades = tuple(face_shade(a, blo, bhi) for a in range(3))
        fs = box_faces(caster, blo, bhi, H, paint, shades, 0.15, fog)  # type: ignore[arg-type]
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
    zenith = np.array(random_rgb(rng, (0.45, 0.8), (0.55, 0.85), 0.6, 0.04), F32)
    sky = lerp(haze, zenith, (np.clip(dy, 0, 1) ** 0.6)[:, None])
    cosang = dx * sun[0] + dy * sun[1] + dz * sun[2]
    glow = (np.clip(cosang, 0, 1) ** 300 * 0.6 + (cosang > math.cos(math.radians(1.5))) * 0.8).astype(F32)
    sky += glow[:, None] * (np.array([255, 250, 230], F32) - sky)
    _add_clouds(rng, sky, (dx, dy, dz), lat, W, H)
    bg = sky.reshape(nb, W, 3)
    _add_mountains(rng, bg, lat, nb, W, haze)
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
        return indoor_scene(rng, width, big=kind == "hall")
    return outdoor_scene(rng, width, village=kind == "village")
