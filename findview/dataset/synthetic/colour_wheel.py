"""The "colour-wheel" toy world: tiny panoramas on which a small PPO agent learns within minutes on a CPU.

The hue turns once around the longitude (random phase), the brightness falls from the top row to the
bottom row, and 30 random discs add local texture. A view's hue tells its yaw almost directly, so a
policy can learn left versus right from few samples; the learning test (``tests/test_learning.py``) and
the batch-scaling benchmark (``benchmarks/bench_lr_scaling.py``) use it.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from findview.utils import atomic_write

__all__ = ["colour_wheel_panorama", "write_colour_wheel_folder"]


def colour_wheel_panorama(seed: int, width: int = 256) -> np.ndarray:
    """A ``(width // 2, width, 3)`` uint8 BGR equirectangular panorama (``width`` in pixels) from ``seed``."""
    if width < 8 or width % 2:
        raise ValueError(f"colour wheel width must be an even number of pixels >= 8, got {width}")
    rng = np.random.default_rng(seed)
    height = width // 2
    u = np.arange(width, dtype=np.float64)[None, :].repeat(height, 0)
    v = np.arange(height, dtype=np.float64)[:, None].repeat(width, 1)
    hue = (rng.integers(0, 180) + 180.0 * u / width) % 180
    value = 50 + 190 * (1 - v / height)
    hsv = np.stack([hue, np.full_like(hue, 200), value], -1).astype(np.uint8)
    image = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    for _ in range(30):
        x, y = (int(c) for c in rng.integers(0, (width, height)))
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cv2.circle(image, (x, y), int(rng.integers(2, height // 10)), colour, -1)
    return image


def write_colour_wheel_folder(root: str | Path, count: int = 10, first_seed: int = 200, width: int = 256) -> list[Path]:
    """Write ``count`` panoramas (seeds ``first_seed ...``) as ``root/pano_XXX.png``; returns their paths."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        path = root / f"pano_{i:03d}.png"
        ok, png = cv2.imencode(".png", colour_wheel_panorama(first_seed + i, width))
        if not ok:
            raise RuntimeError(f"OpenCV could not encode {path} as PNG")
        atomic_write(path, lambda tmp, data=png.tobytes(): Path(tmp).write_bytes(data))
        paths.append(path)
    return paths
