"""Helpers of the training tests (tiny setup: 48x48 views, 2 envs, 8-step rollouts, GRU 32, 300-step
episodes, a 10-panorama folder data set of 256x128 textured images, 3 val episodes)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from omegaconf import DictConfig

from findview_baselines.cli import compose_config

SIZE = 48


def blob_panorama(seed: int, width: int = 256) -> np.ndarray:
    """A cheap textured equirectangular image (``width/2 x width`` RGB): smooth colour noise plus shapes."""
    rng = np.random.default_rng(seed)
    height = width // 2
    coarse = rng.integers(0, 256, (4, 8, 3), dtype=np.uint8)
    image = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(40):
        x, y = (int(v) for v in rng.integers(0, (width, height)))
        size = int(rng.integers(3, height // 6))
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        if rng.random() < 0.5:
            cv2.circle(image, (x, y), size, colour, -1)
        else:
            cv2.rectangle(image, (x, y), (x + size, y + size // 2), colour, -1)
    return image


def write_panoramas(root: Path, make: Any, seeds: Any, label: str) -> list:
    """``make(seed)`` (a BGR image) written as ``root/pano_<i>.png`` for each seed; their
    :class:`~findview.dataset.ImageEntry` rows with ``label``."""
    from findview.dataset import ImageEntry

    entries = []
    for i, seed in enumerate(seeds):
        path = root / f"pano_{i}.png"
        cv2.imwrite(str(path), make(seed))
        entries.append(ImageEntry(str(path), label))
    return entries


def _value(v: Any) -> str:
    return "null" if v is None else str(v)


def make_config(root: Path, out_dir: Path, **overrides: Any) -> DictConfig:
    """configs/train.yaml composed like tools/train.py does, on the ``folder`` data set at ``root`` (3 val
    episodes: 1 image x 3 difficulties), with the tiny test settings, then ``overrides``."""
    tiny = {
        "dataset": "folder", "dataset.root": root, "dataset.out_dir": out_dir, "dataset.name": "testfolder",
        "sim.height": SIZE, "sim.width": SIZE, "sim.device": "cpu", "sim.prefetch_workers": 0,
        "task.max_steps": 300,
        "agent.hidden_size": 32,
        "trainer.num_updates": 6, "trainer.num_envs": 2, "trainer.val_interval": 3, "trainer.val_episodes": 3,
        "trainer.log_interval": 1, "trainer.checkpoint_interval": 2, "trainer.progress": False,
        "trainer.torch_threads": 1,  # fastest on a busy 2-core machine (2 threads oversubscribe)
    }
    if overrides.get("trainer", "ppo") == "ppo":  # a key of the trainer that does not run is refused
        tiny.update({"trainer.ppo.rollout_steps": 8, "trainer.ppo.ppo_epochs": 2})
    return compose_config("train", [f"{k}={_value(v)}" for k, v in {**tiny, **overrides}.items()])


def load(path: Path) -> dict[str, Any]:
    return torch.load(path, map_location="cpu", weights_only=True)


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()
