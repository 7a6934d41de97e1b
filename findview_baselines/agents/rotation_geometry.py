"""The geometry of the ``rotation`` agent: the relative rotation between the current view and the target,
estimated from feature matches with the known pinhole geometry (docs/TASK.md, world), and its
decomposition into pitch and yaw moves.

Geometry. A view pixel ``(x, y)`` (OpenCV keypoint coordinates, pixel centres at integers) has the
camera-frame bearing ``d = ((x + 0.5 - W/2) / f', -(y + 0.5 - H/2) / f', 1)``, ``f' = W / (2 tan(fov/2))``.
A view at ``(pitch p, yaw y)`` maps bearings to the world with ``R(p, y) = Ry(y) Rx(p)``. A scene point
seen at ``d_c`` in the current view and ``d_t`` in the target satisfies ``d_c ~ R_rel d_t`` with

    R_rel = R_c^T R_t = Rx(-p_c) Ry(y_t - y_c) Rx(p_t)

an X-Y-X Euler product. We fit ``R_rel`` to the matched unit bearings with RANSAC over 2-match samples
(Kabsch/SVD fits) and refit on the inliers, then read off

- ``dyaw = y_t - y_c``: ``cos dyaw = R[0,0]``, ``sin dyaw = ±|R[0,1:]|`` with the sign of
  ``R[0,2] - R[2,0] = sin(dyaw) (cos p_t + cos p_c)`` (pitches are within +-90 degrees);
- ``dpitch = p_t - p_c = atan2(R[1,2] - R[2,1], R[1,1] + R[2,2])`` (exact for any ``dyaw != 180``);
- when ``|sin dyaw|`` is large enough, even the absolute pitches ``p_c = -atan2(-R[1,0], -R[2,0])`` and
  ``p_t = atan2(-R[0,1], R[0,2])`` (up to the sign of ``sin dyaw``), used to reject implausible fits.

The estimate is sub-degree (sub-pixel keypoints, a least-squares fit on tens of inliers), so rounding
it gives the exact integer moves.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from findview.geometry import focal_length
from findview_baselines.agents.feature_base import Features, detect, match_features

__all__ = [
    "RotationEstimate",
    "pixel_bearings",
    "kabsch",
    "decompose_relative_rotation",
    "estimate_relative_rotation",
    "estimate_from_features",
    "estimate_from_images",
]


def pixel_bearings(pts: np.ndarray, fov: float, height: int, width: int) -> np.ndarray:
    """Unit camera-frame bearings ``(M, 3)`` float64 (x right, y up, z forward) of keypoints.

    Args:
        pts: ``(M, 2)`` keypoint positions ``(x, y)`` in pixels (OpenCV: pixel centres at integers).
        fov: horizontal field of view, degrees.
        height, width: view size, pixels.
    """
    f = focal_length(fov, width)
    p = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
    d = np.empty((p.shape[0], 3), np.float64)
    d[:, 0] = (p[:, 0] + 0.5 - width / 2.0) / f
    d[:, 1] = -(p[:, 1] + 0.5 - height / 2.0) / f
    d[:, 2] = 1.0
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotation(s) ``R`` minimising ``sum ||dst - R src||^2``.

    Args:
        src, dst: ``(..., M, 3)`` corresponding unit vectors (batched over leading dims).

    Returns:
        ``(..., 3, 3)`` proper rotations (det +1).
    """
    h = np.einsum("...mi,...mj->...ij", src, dst)  # sum src dst^T
    u, _, vt = np.linalg.svd(h)
    v = np.swapaxes(vt, -1, -2)
    ut = np.swapaxes(u, -1, -2)
    det = np.linalg.det(v @ ut)
    corr = np.ones(h.shape[:-2] + (3,))
    corr[..., 2] = np.sign(det) + (det == 0)
    return (v * corr[..., None, :]) @ ut


@dataclass
class RotationEstimate:
    """Relative rotation of the target w.r.t. the current view (degrees).

    Attributes:
        dpitch: ``p_target - p_current``.
        dyaw: ``y_target - y_current`` in ``(-180, 180]``.
        pitch_current, pitch_target: absolute pitches, ``nan`` when not observable (``dyaw`` near 0).
        inliers: number of RANSAC inliers; matches: number of candidate matches.
        valid: enough inliers and plausible pitches.
        rotation: ``(3, 3)`` fitted ``R_rel`` (maps target bearings to current bearings), or ``None``.
    """

    dpitch: float = math.nan
    dyaw: float = math.nan
    pitch_current: float = math.nan
    pitch_target: float = math.nan
    inliers: int = 0
    matches: int = 0
    valid: bool = False
    rotation: np.ndarray | None = field(default=None, repr=False)

    def rounded(self) -> tuple[int, int]:
        """``(round(dpitch), round(dyaw))`` as ints (the moves to make)."""
        return int(round(self.dpitch)), int(round(self.dyaw))


def decompose_relative_rotation(r: np.ndarray, min_sin: float = 0.1) -> tuple[float, float, float, float]:
    """``R_rel = Rx(-p_c) Ry(dyaw) Rx(p_t)`` -> ``(dpitch, dyaw, p_c, p_t)`` in degrees.

    ``p_c, p_t`` are ``nan`` when ``|sin dyaw| < min_sin`` (then only their difference is well defined).
    Assumes ``|p_c|, |p_t| < 90``.
    """
    dpitch = math.atan2(r[1, 2] - r[2, 1], r[1, 1] + r[2, 2])
    s_abs = 0.5 * (math.hypot(r[0, 1], r[0, 2]) + math.hypot(r[1, 0], r[2, 0]))
    sign = 1.0 if (r[0, 2] - r[2, 0]) >= 0 else -1.0
    dyaw = math.atan2(sign * s_abs, r[0, 0])
    p_c = p_t = math.nan
    if s_abs >= min_sin:
        p_t = math.atan2(-sign * r[0, 1], sign * r[0, 2])
        p_c = -math.atan2(-sign * r[1, 0], -sign * r[2, 0])
        p_c, p_t = math.degrees(p_c), math.degrees(p_t)
    return math.degrees(dpitch), math.degrees(dyaw), p_c, p_t


def estimate_relative_rotation(
    bear_cur: np.ndarray,
    bear_tgt: np.ndarray,
    rng: np.random.Generator,
    inlier_rad: float,
    iterations: int = 200,
    min_inliers: int = 5,
    pitch_limit: float = 70.0,
) -> RotationEstimate:
    """RANSAC + Kabsch fit of ``R_rel`` with ``bear_cur ~ R_rel bear_tgt``.

    Args:
        bear_cur, bear_tgt: ``(M, 3)`` unit bearings of the matched keypoints (current, target).
        rng: randomness of the 2-match samples.
        inlier_rad: a match is an inlier when the angle between ``bear_cur`` and ``R bear_tgt`` is below
            this (radians).
        iterations: RANSAC hypotheses.
        min_inliers: fewer inliers -> ``valid = False``.
        pitch_limit: observable absolute pitches beyond this (degrees) -> ``valid = False``.
    """
    m = bear_cur.shape[0]
    est = RotationEstimate(matches=m)
    if m < 2 or m < min_inliers:
        return est
    # sample pairs (i != j); batched 2-point Kabsch fits
    i = rng.integers(0, m, size=iterations)
    j = (i + rng.integers(1, m, size=iterations)) % m
    src = np.stack([bear_tgt[i], bear_tgt[j]], axis=1)  # (K, 2, 3)
    dst = np.stack([bear_cur[i], bear_cur[j]], axis=1)
    sep = np.linalg.norm(np.cross(src[:, 0], src[:, 1]), axis=1)
    ok = sep > 1e-3
    if not ok.any():
        return est
    rots = kabsch(src[ok], dst[ok])  # (K', 3, 3)
    cos_thr = math.cos(inlier_rad)
    # cos(angle(c_m, R t_m)) = sum_ij c_mi R_ij t_mj: one (K', 9) x (9, M) product
    outer = (bear_cur[:, :, None] * bear_tgt[:, None, :]).reshape(m, 9)
    cosines = rots.reshape(-1, 9) @ outer.T  # (K', M)
    counts = (cosines > cos_thr).sum(axis=1)
    best = int(np.argmax(counts))
    inl = cosines[best] > cos_thr
    r = rots[best]
    for _ in range(2):  # refit on the inliers, recompute them
        if inl.sum() < 2:
            break
        r = kabsch(bear_tgt[inl], bear_cur[inl])
        inl = (bear_cur * (bear_tgt @ r.T)).sum(axis=1) > cos_thr
    n_in = int(inl.sum())
    dpitch, dyaw, p_c, p_t = decompose_relative_rotation(r)
    plausible = not (abs(p_c) > pitch_limit or abs(p_t) > pitch_limit)  # nan compares False
    return RotationEstimate(
        dpitch=dpitch,
        dyaw=dyaw,
        pitch_current=p_c,
        pitch_target=p_t,
        inliers=n_in,
        matches=m,
        valid=bool(n_in >= min_inliers and plausible),
        rotation=r,
    )


def estimate_from_features(
    cur: Features,
    tgt: Features,
    fov: float,
    height: int,
    width: int,
    rng: np.random.Generator,
    detector: str = "sift",
    ratio: float = 0.8,
    inlier_px: float = 2.0,
    iterations: int = 200,
    min_inliers: int = 5,
    pitch_limit: float = 70.0,
) -> RotationEstimate:
    """Match ``cur`` to ``tgt`` (ratio test) and fit the relative rotation (see
    :func:`estimate_relative_rotation`); ``inlier_px`` is the inlier tolerance in pixels at the centre."""
    ci, ti, _ = match_features(cur, tgt, detector, ratio)
    if len(ci) < max(2, min_inliers):
        return RotationEstimate(matches=len(ci))
    bc = pixel_bearings(cur.pts[ci], fov, height, width)
    bt = pixel_bearings(tgt.pts[ti], fov, height, width)
    inlier_rad = math.atan(inlier_px / focal_length(fov, width))
    return estimate_relative_rotation(bc, bt, rng, inlier_rad, iterations, min_inliers, pitch_limit)


def estimate_from_images(
    view_gray: np.ndarray,
    target_gray: np.ndarray,
    fov: float,
    rng: np.random.Generator | None = None,
    detector: str = "sift",
    n_features: int = 500,
    **kw: Any,
) -> RotationEstimate:
    """Convenience: estimate the target's rotation relative to the current view from two ``(H, W)``
    uint8 gray images (same size)."""
    if view_gray.shape != target_gray.shape:
        raise ValueError(f"view {view_gray.shape} and target {target_gray.shape} must have the same size")
    h, w = view_gray.shape[:2]
    cur = detect(detector, view_gray, n_features)
    tgt = detect(detector, target_gray, n_features)
    return estimate_from_features(
        cur, tgt, fov, h, w, rng if rng is not None else np.random.default_rng(0), detector=detector, **kw
    )
