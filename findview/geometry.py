"""Rotation arithmetic on integer-degree (pitch, yaw) pairs.

Conventions (docs/TASK.md, World and camera; Metrics): ``+pitch`` looks up, ``+yaw`` pans right, yaw
lives in ``(-180, 180]``, distances are in degrees. Functions accept Python ints, numpy arrays or torch tensors.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

__all__ = ["wrap_yaw", "yaw_diff", "l1_distance", "l2_distance", "focal_length"]


def wrap_yaw(yaw: Any) -> Any:
    """Wrap yaw (degrees) into ``(-180, 180]``; works on ints, arrays and tensors."""
    if isinstance(yaw, torch.Tensor):
        return 180 - torch.remainder(180 - yaw, 360)
    if isinstance(yaw, np.ndarray):
        return 180 - np.mod(180 - yaw, 360)
    return 180 - ((180 - yaw) % 360)


def yaw_diff(a: Any, b: Any) -> Any:
    """Wrapped absolute yaw difference ``min(|a-b|, 360-|a-b|)`` in degrees (inputs in any range)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        d = torch.remainder(torch.as_tensor(a) - torch.as_tensor(b), 360)
        return torch.minimum(d, 360 - d)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        d = np.mod(np.asarray(a) - np.asarray(b), 360)
        return np.minimum(d, 360 - d)
    d = (a - b) % 360
    return min(d, 360 - d)


def l1_distance(pitch_a: Any, yaw_a: Any, pitch_b: Any, yaw_b: Any) -> Any:
    """``|dpitch| + dyaw`` (degrees): the localization error and the shortest path length."""
    if isinstance(pitch_a, torch.Tensor) or isinstance(pitch_b, torch.Tensor):
        return (torch.as_tensor(pitch_a) - torch.as_tensor(pitch_b)).abs() + yaw_diff(yaw_a, yaw_b)
    if isinstance(pitch_a, np.ndarray) or isinstance(pitch_b, np.ndarray):
        return np.abs(np.asarray(pitch_a) - np.asarray(pitch_b)) + yaw_diff(yaw_a, yaw_b)
    return abs(pitch_a - pitch_b) + yaw_diff(yaw_a, yaw_b)


def l2_distance(pitch_a: Any, yaw_a: Any, pitch_b: Any, yaw_b: Any) -> Any:
    """``sqrt(dpitch^2 + dyaw^2)`` (degrees) with the wrapped yaw difference."""
    dy = yaw_diff(yaw_a, yaw_b)
    if isinstance(dy, torch.Tensor):
        dp = (torch.as_tensor(pitch_a) - torch.as_tensor(pitch_b)).to(torch.float64)
        return torch.sqrt(dp**2 + dy.to(torch.float64) ** 2)
    if isinstance(dy, np.ndarray):
        dp = np.asarray(pitch_a, dtype=np.float64) - np.asarray(pitch_b, dtype=np.float64)
        return np.sqrt(dp**2 + dy.astype(np.float64) ** 2)
    return math.sqrt((pitch_a - pitch_b) ** 2 + dy**2)


def focal_length(fov_deg: float, width: int) -> float:
    """Pinhole focal length in pixels, ``f' = W / (2 tan(fov/2))`` for horizontal FoV ``fov_deg``."""
    if not 0.0 < float(fov_deg) < 180.0:
        raise ValueError(f"fov must be in (0, 180) degrees, got {fov_deg!r}")
    return width / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
