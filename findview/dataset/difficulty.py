"""Difficulty rules and the (init, target) rotation distribution (docs/TASK.md, Difficulties).

With ``dpitch = |pitch_init - pitch_target|`` and the wrapped ``dyaw`` (:func:`findview.geometry.yaw_diff`),
``L1 = dpitch + dyaw``, ``L2 = sqrt(dpitch^2 + dyaw^2)`` (degrees) and the horizontal FoV ``f`` (degrees):

- every episode: ``10 < L1 < max_steps``;
- ``easy``:   ``L2 <= sqrt(2) * f / 2`` (checked exactly as ``L2^2 <= f^2 / 2``);
- ``medium``: ``f/2 < L1 <= f``;
- ``hard``:   ``dpitch > f OR dyaw > f`` (``hard_rule="or"``, the default: the rule behind the paper's
  published numbers) or ``dpitch > f AND dyaw > f`` (``hard_rule="and"``, the paper's text).

Rotations are integer degrees: pitch in ``[-pitch_bound, pitch_bound]`` with probability proportional to
the normal density of ``pitch / 60`` (mean 0, std 0.3, i.e. std 18 degrees; the 60 is fixed, it does not
follow ``pitch_bound``), yaw uniform in ``(-180, 180]``; init and target independent.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from findview.episode import DIFFICULTIES
from findview.geometry import yaw_diff

__all__ = [
    "DIFFICULTIES",
    "HARD_RULES",
    "PITCH_SCALE",
    "PITCH_STD",
    "MIN_PATH",
    "check_difficulty",
    "check_fov",
    "check_pitch_bound",
    "check_hard_rule",
    "difficulty_mask",
    "satisfies",
    "pitch_distribution",
]

HARD_RULES = ("or", "and")
PITCH_SCALE = 60.0  # pitch / PITCH_SCALE ~ N(0, PITCH_STD^2)
PITCH_STD = 0.3
MIN_PATH = 10  # every episode has L1 > MIN_PATH


def check_difficulty(difficulty: str) -> str:
    """Return ``difficulty`` or raise ``ValueError`` listing the valid ones."""
    if difficulty not in DIFFICULTIES:
        raise ValueError(f"unknown difficulty {difficulty!r}; valid: {', '.join(DIFFICULTIES)}")
    return difficulty


def check_fov(fov: float) -> float:
    """Return ``fov`` (degrees) as float or raise ``ValueError`` unless it lies in ``(0, 180)``."""
    try:
        f = float(fov)
    except (TypeError, ValueError) as e:
        raise ValueError(f"fov must be a number of degrees in (0, 180), got {fov!r}") from e
    if not 0.0 < f < 180.0 or math.isnan(f):
        raise ValueError(f"fov must be in (0, 180) degrees, got {fov!r}")
    return f


def check_pitch_bound(pitch_bound: int) -> int:
    """Return ``pitch_bound`` (degrees) or raise ``ValueError`` unless it is an integer in ``[0, 90]``."""
    if isinstance(pitch_bound, bool) or int(pitch_bound) != pitch_bound:
        raise ValueError(f"pitch_bound must be an integer number of degrees, got {pitch_bound!r}")
    pb = int(pitch_bound)
    if not 0 <= pb <= 90:
        raise ValueError(f"pitch_bound must be in [0, 90] degrees, got {pitch_bound!r}")
    return pb


def check_hard_rule(hard_rule: str) -> str:
    """Return ``hard_rule`` lower-cased or raise ``ValueError`` unless it is ``or`` / ``and``."""
    rule = str(hard_rule).lower()
    if rule not in HARD_RULES:
        raise ValueError(f"unknown hard_rule {hard_rule!r}; valid: {', '.join(HARD_RULES)}")
    return rule


def difficulty_mask(
    dpitch: Any,
    dyaw: Any,
    difficulty: str,
    fov: float,
    max_steps: int = 5000,
    hard_rule: str = "or",
) -> np.ndarray:
    """Boolean mask: which ``(dpitch, dyaw)`` pairs (degrees, arrays, ``dyaw`` already wrapped to
    ``[0, 180]``) satisfy ``difficulty`` at horizontal FoV ``fov`` and ``10 < L1 < max_steps``."""
    check_difficulty(difficulty)
    f = check_fov(fov)
    rule = check_hard_rule(hard_rule)
    dp = np.abs(np.asarray(dpitch, dtype=np.int64))
    dy = np.asarray(dyaw, dtype=np.int64)
    l1 = dp + dy
    ok = (l1 > MIN_PATH) & (l1 < max_steps)
    if difficulty == "easy":
        # L2 <= sqrt(2) f / 2  <=>  L2^2 <= f^2 / 2 (exact for integer distances)
        return ok & ((dp * dp + dy * dy) <= f * f / 2.0)
    if difficulty == "medium":
        return ok & (l1 > f / 2.0) & (l1 <= f)
    if rule == "or":
        return ok & ((dp > f) | (dy > f))
    return ok & ((dp > f) & (dy > f))


def satisfies(
    init_pitch: int,
    init_yaw: int,
    target_pitch: int,
    target_yaw: int,
    difficulty: str,
    fov: float,
    max_steps: int = 5000,
    hard_rule: str = "or",
) -> bool:
    """Whether one (init, target) rotation pair (integer degrees) meets ``difficulty`` at ``fov``."""
    dp = abs(int(init_pitch) - int(target_pitch))
    dy = yaw_diff(int(init_yaw), int(target_yaw))
    return bool(difficulty_mask(np.array([dp]), np.array([dy]), difficulty, fov, max_steps, hard_rule)[0])


def pitch_distribution(pitch_bound: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Integer pitches ``[-pitch_bound, pitch_bound]`` (degrees, int64) and their probabilities.

    ``p(pitch) ∝ exp(-(pitch / 60)^2 / (2 * 0.3^2))``.
    """
    pb = check_pitch_bound(pitch_bound)
    values = np.arange(-pb, pb + 1, dtype=np.int64)
    z = values / PITCH_SCALE / PITCH_STD
    w = np.exp(-0.5 * z * z)
    return values, w / w.sum()
