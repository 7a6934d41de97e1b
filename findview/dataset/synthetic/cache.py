"""The on-disk synthetic data set: ``<root>/<label>/synth_XXXX.jpg`` plus the manifest
``<root>/synthetic.json``, generated once and regenerated only when its parameters change.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import cv2

from findview.dataset.discovery import DatasetError, ImageEntry
from findview.dataset.synthetic.scenes import SCENE_KINDS, generate_panorama
from findview.utils import atomic_write, read_json, write_json

__all__ = ["GENERATOR_VERSION", "MANIFEST", "synthetic_image_seed", "ensure_synthetic_images"]

GENERATOR_VERSION = 1
MANIFEST = "synthetic.json"


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
