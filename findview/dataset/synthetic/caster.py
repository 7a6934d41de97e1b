"""The panorama ray caster: per-pixel nearest hit over planes and axis-aligned boxes, then textured
shading with mip-mapping.

The camera sits at the origin; +x is right, +y up, +z forward (longitude 0). Pixel ``(v, u)`` of a
``W x H`` panorama (``H = W / 2``) looks along longitude ``lon = ((u + 0.5) / W - 0.5) * 360`` degrees
and latitude ``lat = 90 - (v + 0.5) / H * 180`` degrees, i.e. the direction
``(cos lat sin lon, sin lat, cos lat cos lon)`` (docs/TASK.md, World and camera). Hits store the
distance ``t`` (metres), the surface id and the surface coordinates ``(u, v)`` in metres; :meth:`Caster.shade`
samples the textures (bilinear, ``MIP_LEVELS`` levels chosen from the pixel footprint).
"""

from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from findview.dataset.synthetic.textures import F32

__all__ = ["MIP_LEVELS", "Surface", "Caster"]


MIP_LEVELS = 3


# ----------------------------------------------------------------------------------------------------
# ray casting
# ----------------------------------------------------------------------------------------------------
class Surface:
    """A textured surface: ``tex`` ``(h, w, 3)`` uint8 at ``ppm`` texels per metre covering ``size_m``
    (metres, ``inf`` for infinite planes), a constant ``shade`` factor, ambient occlusion strength ``ao``
    near its edges, aerial-perspective distance ``fog`` (metres) and whether the texture tiles (``wrap``)."""

    def __init__(self, tex: np.ndarray, ppm: float, size_m: tuple[float, float], shade: float = 1.0,
                 ao: float = 0.0, fog: float = math.inf, wrap: bool = False) -> None:
        self.tex, self.ppm, self.size_m, self.shade, self.ao, self.fog, self.wrap = tex, ppm, size_m, shade, ao, fog, wrap


class Caster:
    """Per-pixel nearest hit ``(t, surface id, u, v)`` over planes and boxes (flat arrays, float32)."""

    def __init__(self, width: int) -> None:
        W, H = width, width // 2
        self.W, self.H = W, H
        lon = ((np.arange(W, dtype=np.float64) + 0.5) / W - 0.5) * 2 * np.pi
        lat = (0.5 - (np.arange(H, dtype=np.float64) + 0.5) / H) * np.pi
        cl = np.cos(lat)[:, None]
        self.lat_deg = np.degrees(lat).astype(F32)
        self.d = [
            (cl * np.sin(lon)[None, :]).astype(F32).ravel(),
            np.repeat(np.sin(lat), W).astype(F32),
            (cl * np.cos(lon)[None, :]).astype(F32).ravel(),
        ]
        with np.errstate(divide="ignore"):
            self.inv = [np.where(np.abs(a) > 1e-9, 1.0 / a, np.float32(1e9)).astype(F32) for a in self.d]
        n = W * H
        self.t = np.full(n, np.inf, F32)
        self.sid = np.full(n, -1, np.int32)
        self.u = np.zeros(n, F32)
        self.v = np.zeros(n, F32)
        self.cos = np.ones(n, F32)
        self.surfaces: list[Surface] = []

    def add_surface(self, s: Surface) -> int:
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
        t_axis = [np.where(self.d[a] > 0, hi[a], lo[a]).astype(F32) * self.inv[a] for a in range(3)]
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
        t = np.where(down, y * self.inv[1], np.inf).astype(F32)
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
        out = np.zeros((n, 3), F32)
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
        ppm = np.array([s.ppm for s in self.surfaces], F32)[sid]
        tw = np.array([t.shape[1] for t in texs], F32)[sid]
        th = np.array([t.shape[0] for t in texs], F32)[sid]
        wrap = np.array([s.wrap for s in self.surfaces], bool)[sid]
        ox = np.array([p[0] for p in pos], F32)[sid]
        oy = np.array([p[1] for p in pos], F32)[sid]
        tx = self.u * ppm - 0.5
        ty = self.v * ppm - 0.5
        tx = np.where(wrap, np.mod(tx, tw), np.clip(tx, 0, tw - 1)) + ox
        ty = np.where(wrap, np.mod(ty, th), np.clip(ty, 0, th - 1)) + oy
        # mip level from the pixel footprint in texels
        foot = np.where(hit, self.t, 0) * (np.pi / self.H) * ppm / np.sqrt(np.maximum(self.cos, 0.3))
        level = np.clip(np.log2(np.maximum(foot, 1e-6)), 0, MIP_LEVELS - 1 - 1e-3).astype(F32)
        lo_l = np.floor(level)
        frac = (level - lo_l)[:, None]
        mips = [atlas]
        for _ in range(MIP_LEVELS - 1):
            mips.append(cv2.pyrDown(mips[-1]))
        samples = []
        for lvl, img in enumerate(mips):
            s = 2.0**lvl
            mx = ((tx + 0.5) / s - 0.5).reshape(self.H, self.W)
            my = ((ty + 0.5) / s - 0.5).reshape(self.H, self.W)
            samples.append(cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(-1, 3))
        for lvl in range(MIP_LEVELS):
            w = np.where(lo_l == lvl, 1 - frac[:, 0], 0) + np.where(lo_l == lvl - 1, frac[:, 0], 0)
            out += samples[lvl].astype(F32) * w[:, None]
        # shading: per-surface factor, darkening near the surface edges (ambient occlusion)
        shade = np.array([s.shade for s in self.surfaces], F32)[sid]
        ao = np.array([s.ao for s in self.surfaces], F32)[sid]
        su = np.array([s.size_m[0] for s in self.surfaces], F32)[sid]
        sv = np.array([s.size_m[1] for s in self.surfaces], F32)[sid]
        with np.errstate(invalid="ignore"):
            edge = np.minimum(np.minimum(self.u, su - self.u), np.minimum(self.v, sv - self.v))
        edge = np.where(np.isfinite(edge), np.maximum(edge, 0), 1e3)
        out *= (shade * (1 - ao * np.exp(-edge / 0.3)))[:, None]
        self.fog = np.array([s.fog for s in self.surfaces], F32)[sid]
        return out, hit

