"""``rotation``: a geometric rule-based agent (beyond the paper).

Instead of voting on pixel displacements, it estimates the full relative rotation between the current
view and the target from feature matches, using the known pinhole geometry (SPEC section 1), and then
walks straight to the target.

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

Policy (per slot):

- WALK: with a valid estimate, the remaining moves ``(round(dpitch), round(dyaw))`` are a plan that the
  agent dead-reckons (every move is exactly 1 degree, and a straight walk to a target inside the pitch
  bounds never hits them), moving along the axis with more remaining moves (a straight-ish line keeps
  the views overlapping). It re-estimates every ``reestimate_every`` moves and whenever the plan is
  used up: an estimate that rounds to ``(0, 0)`` ends the episode with STOP, any other replaces the plan.
  A lost track (no valid estimate) keeps walking the last plan; on arrival without a valid estimate it
  STOPs (the best guess) once the target has been seen, else sweeps.
- SWEEP (nothing to match, e.g. the hard episodes with no overlap): a full 360-degree yaw turn in one
  seeded direction, then the pitch moves to the next level of ``0, +s, -s, +2s, -2s`` degrees relative to
  the start (``s = sweep_pitch``, default fov/2), and so on; it tries an estimate every
  ``sweep_check_every`` steps.
- Guards: after ``max_arrivals`` arrivals whose check asks for more moves, it STOPs.

A valid estimate needs ``min_inliers`` inliers and plausible absolute pitches (within
``pitch_bound + pitch_tol``) when they are observable.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from findview.episode import Episode
from findview.geometry import focal_length
from findview_baselines.agents.base import (
    DOWN,
    LEFT,
    RIGHT,
    STOP,
    UP,
    Agent,
    check_keys,
    episode_rng,
    rgb_to_gray,
    to_plain_dict,
)
from findview_baselines.agents.feature_matching import (
    DETECTORS,
    Features,
    ParallelRunner,
    cv2_num_threads,
    detect,
    match_features,
)

__all__ = [
    "RotationEstimate",
    "pixel_bearings",
    "kabsch",
    "decompose_relative_rotation",
    "estimate_relative_rotation",
    "estimate_from_features",
    "RotationAgent",
]


# --------------------------------------------------------------------------------------------------
# geometry
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# the agent
# --------------------------------------------------------------------------------------------------
WALK, SWEEP = "walk", "sweep"


@dataclass
class _Slot:
    rng: np.random.Generator
    target: Features | None = None
    mode: str = SWEEP
    plan_p: int = 0  # remaining pitch moves (+ up)
    plan_y: int = 0  # remaining yaw moves (+ right)
    since_est: int = 10**9  # moves since the last estimate attempt
    seen: bool = False  # a valid estimate happened this episode
    arrivals: int = 0
    sweep_dir: int = RIGHT
    sweep_yaw: int = 0  # yaw moves done on the current sweep level
    sweep_level: int = 0
    sweep_pitch_todo: int = 0  # pitch moves left to reach the current level (+ up)
    done: bool = False
    last: RotationEstimate | None = None


class RotationAgent(Agent):
    """Relative-rotation estimation + dead-reckoned straight walk (see the module docstring).

    Args:
        num_envs, device, seed: see :class:`~findview_baselines.agents.base.Agent`.
        fov: horizontal field of view of the views, degrees (must match the simulator).
        detector: ``"sift"`` (default) or ``"orb"``; n_features: keypoints per image (500).
        ratio: Lowe ratio for the candidate matches (0.8; RANSAC removes the outliers).
        inlier_px: RANSAC inlier tolerance, pixels at the image centre (2.0).
        ransac_iters: RANSAC hypotheses (200).
        min_inliers: inliers for a valid estimate (5; on 216 SIFT view pairs of sun360_mini, 5 gave no
            wrong estimate, 4 gave 3).
        pitch_bound: the task's pitch clamp (60); pitch_tol: slack on it for plausibility (10).
        reestimate_every: moves between estimates while walking (4).
        sweep_check_every: moves between estimate attempts while sweeping (3).
        sweep_pitch: pitch change between sweep levels, degrees (``None``: ``round(fov / 2)``).
        max_arrivals: arrivals that ask for more moves before giving up with STOP (6).
        threads: worker threads over slots (2); cv2_threads: OpenCV threads while acting (1; ``None``:
            leave OpenCV's setting alone).
    """

    name = "rotation"
    CONFIG_KEYS = (
        "fov",
        "detector",
        "n_features",
        "ratio",
        "inlier_px",
        "ransac_iters",
        "min_inliers",
        "pitch_bound",
        "pitch_tol",
        "reestimate_every",
        "sweep_check_every",
        "sweep_pitch",
        "max_arrivals",
        "threads",
        "cv2_threads",
    )

    def __init__(
        self,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        fov: float = 90.0,
        detector: str = "sift",
        n_features: int = 500,
        ratio: float = 0.8,
        inlier_px: float = 2.0,
        ransac_iters: int = 200,
        min_inliers: int = 5,
        pitch_bound: int = 60,
        pitch_tol: float = 10.0,
        reestimate_every: int = 4,
        sweep_check_every: int = 3,
        sweep_pitch: int | None = None,
        max_arrivals: int = 6,
        threads: int = 2,
        cv2_threads: int | None = 1,
    ) -> None:
        super().__init__(num_envs, device, seed)
        if detector not in DETECTORS:
            raise ValueError(f"unknown detector {detector!r}; expected one of {DETECTORS}")
        focal_length(fov, 1)  # validates fov
        self.fov = float(fov)
        self.detector = detector
        self.n_features = int(n_features)
        self.ratio = float(ratio)
        self.inlier_px = float(inlier_px)
        self.ransac_iters = int(ransac_iters)
        self.min_inliers = int(min_inliers)
        self.pitch_bound = int(pitch_bound)
        self.pitch_limit = float(pitch_bound) + float(pitch_tol)
        self.reestimate_every = max(1, int(reestimate_every))
        self.sweep_check_every = max(1, int(sweep_check_every))
        self.sweep_pitch = int(round(self.fov / 2)) if sweep_pitch is None else int(sweep_pitch)
        self.max_arrivals = int(max_arrivals)
        s = self.sweep_pitch
        self.levels = [0, s, -s, 2 * s, -2 * s]
        self.cv2_threads = None if cv2_threads is None else int(cv2_threads)
        self.runner = ParallelRunner(threads)
        self._rng = np.random.default_rng(self.seed)
        self.slots = [self._fresh(None) for _ in range(self.num_envs)]

    @classmethod
    def from_config(cls, cfg: Any, num_envs: int, device: str | torch.device, seed: int) -> "RotationAgent":
        c = to_plain_dict(cfg)
        check_keys(cls.name, c, cls.CONFIG_KEYS)
        return cls(num_envs, device, seed, **{k: c[k] for k in cls.CONFIG_KEYS if k in c})

    def _fresh(self, ep: Episode | None) -> _Slot:
        rng = episode_rng(self.seed, ep, self._rng)
        return _Slot(rng=rng, sweep_dir=LEFT if rng.integers(0, 2) == 0 else RIGHT)

    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        """Start ``episodes`` in slots ``env_ids``; a ``None`` episode idles the slot (STOP, no work)."""
        super().reset(env_ids, episodes)
        for i, ep in zip(env_ids, episodes):
            self.slots[int(i)] = self._fresh(ep)
            self.slots[int(i)].done = ep is None

    # policy --------------------------------------------------------------------------------------
    def needs_estimate(self, s: _Slot) -> bool:
        """Whether the slot looks at its current view this step."""
        if s.done:
            return False
        if s.mode == WALK:
            return (s.plan_p == 0 and s.plan_y == 0) or s.since_est >= self.reestimate_every
        return s.since_est >= self.sweep_check_every

    def _walk_move(self, s: _Slot) -> int:
        if abs(s.plan_y) >= abs(s.plan_p) and s.plan_y != 0:
            a = RIGHT if s.plan_y > 0 else LEFT
            s.plan_y -= 1 if s.plan_y > 0 else -1
        else:
            a = UP if s.plan_p > 0 else DOWN
            s.plan_p -= 1 if s.plan_p > 0 else -1
        return a

    def _sweep_move(self, s: _Slot) -> int:
        if s.sweep_pitch_todo != 0:
            a = UP if s.sweep_pitch_todo > 0 else DOWN
            s.sweep_pitch_todo -= 1 if s.sweep_pitch_todo > 0 else -1
            return a
        if s.sweep_yaw >= 360:  # level done: go to the next pitch level
            nxt = (s.sweep_level + 1) % len(self.levels)
            s.sweep_pitch_todo = self.levels[nxt] - self.levels[s.sweep_level]
            s.sweep_level = nxt
            s.sweep_yaw = 0
            if s.sweep_pitch_todo != 0:
                return self._sweep_move(s)
        s.sweep_yaw += 1
        return s.sweep_dir

    def decide(self, s: _Slot, est: RotationEstimate | None) -> int:
        """One step of the slot's policy given this step's estimate (``None``: none attempted)."""
        if est is not None:
            s.since_est = 0
            s.last = est
            if est.valid:
                s.seen = True
                dp, dy = est.rounded()
                if dp == 0 and dy == 0:
                    s.done = True
                    return STOP
                if s.mode == WALK and s.plan_p == 0 and s.plan_y == 0:
                    s.arrivals += 1
                    if s.arrivals >= self.max_arrivals:
                        s.done = True
                        return STOP
                s.mode = WALK
                s.plan_p, s.plan_y = dp, dy
            elif s.mode == WALK and s.plan_p == 0 and s.plan_y == 0:
                # arrived, cannot check: the target was seen -> best guess; never seen -> sweep
                if s.seen:
                    s.done = True
                    return STOP
                s.mode = SWEEP
        if s.mode == WALK and (s.plan_p != 0 or s.plan_y != 0):
            a = self._walk_move(s)
        else:
            s.mode = SWEEP
            a = self._sweep_move(s)
        s.since_est += 1
        return a

    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, target = self._check_obs(obs)
        n, _, h, w = view.shape
        actions = np.full(n, STOP, dtype=np.int64)
        active = [i for i, s in enumerate(self.slots) if not s.done]
        if not active:
            return self._as_actions(actions, view.device)
        look = [i for i in active if self.needs_estimate(self.slots[i])]
        need_t = [i for i in look if self.slots[i].target is None]
        gv = rgb_to_gray(view[look]) if look else None
        gt = rgb_to_gray(target[need_t]) if need_t else None
        pos_v = {i: k for k, i in enumerate(look)}
        pos_t = {i: k for k, i in enumerate(need_t)}

        def step(i: int) -> int:
            s = self.slots[i]
            est = None
            if i in pos_v:
                if s.target is None:
                    s.target = detect(self.detector, gt[pos_t[i]], self.n_features)  # type: ignore[index]
                cur = detect(self.detector, gv[pos_v[i]], self.n_features)  # type: ignore[index]
                est = estimate_from_features(
                    cur,
                    s.target,
                    self.fov,
                    h,
                    w,
                    s.rng,
                    detector=self.detector,
                    ratio=self.ratio,
                    inlier_px=self.inlier_px,
                    iterations=self.ransac_iters,
                    min_inliers=self.min_inliers,
                    pitch_limit=self.pitch_limit,
                )
            return self.decide(s, est)

        heavy = [i for i in active if i in pos_v]
        light = [i for i in active if i not in pos_v]
        with cv2_num_threads(self.cv2_threads if len(heavy) > 1 else None):
            results = self.runner.map(step, heavy)
        for i, a in zip(heavy, results):
            actions[i] = a
        for i in light:
            actions[i] = step(i)
        return self._as_actions(actions, view.device)

    def close(self) -> None:
        """Stop the worker threads."""
        self.runner.close()
