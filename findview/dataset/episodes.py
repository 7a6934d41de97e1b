"""Static (val / test) episode files: ``<out_dir>/episodes/<split>_fov<F:g>.json``.

For a split, a FoV ``F`` and ``K = episodes_per_image``, the file holds, for each difficulty in
``easy, medium, hard`` (in that order), for each image of the split (in ``splits.json`` order), ``K``
episodes. The rotations come from :func:`findview.dataset.sampler.sample_rotations` with a generator
seeded by ``(seed, split, F, difficulty)``, so the same inputs always give a byte-identical file.
Episode ids are ``"<split>-fov<F:g>-<difficulty>-<image index:06d>-<k>"``; the episode seed is
:func:`findview.dataset.sampler.derive_seed` of ``(seed, split, F, id)``.

The file is JSON (header keys first, then one episode per line, images relative to ``root``)::

    {"dataset": ..., "root": ..., "split": ..., "fov": ..., "hard_rule": ..., "seed": ...,
     ..., "episodes": [{...}, ...]}
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from findview.dataset.difficulty import check_fov, check_hard_rule, check_pitch_bound
from findview.dataset.discovery import DatasetError, ImageEntry
from findview.dataset.sampler import DEFAULT_MAX_TRIES, derive_seed, sample_rotations
from findview.dataset.splits import MAKE_DATASET_HINT, SPLITS, relative_image_path
from findview.episode import DIFFICULTIES, Episode
from findview.utils import read_json, write_text

__all__ = ["episode_file", "fov_tag", "make_static_episodes", "write_episode_file", "load_episodes", "read_episode_file"]


def fov_tag(fov: float) -> str:
    """``f"{fov:g}"`` with integral FoVs written without a decimal point (``90``, ``67.5``)."""
    return f"{float(fov):g}"


def _fov_json(fov: float) -> int | float:
    f = float(fov)
    return int(f) if f.is_integer() else f


def episode_file(out_dir: str | os.PathLike, split: str, fov: float) -> Path:
    """``<out_dir>/episodes/<split>_fov<F:g>.json`` (e.g. ``episodes/test_fov90.json``)."""
    return Path(out_dir) / "episodes" / f"{split}_fov{fov_tag(fov)}.json"


def make_static_episodes(
    images: Sequence[ImageEntry],
    split: str,
    fov: float,
    episodes_per_image: int = 1,
    seed: int = 0,
    pitch_bound: int = 60,
    max_steps: int = 5000,
    hard_rule: str = "or",
    difficulties: Sequence[str] = DIFFICULTIES,
    max_tries: int = DEFAULT_MAX_TRIES,
) -> list[Episode]:
    """``K = episodes_per_image`` seeded episodes per image per difficulty (see module docstring).

    Args:
        images: the split's images (absolute paths).
        split: split name (part of the ids and of the seed).
        fov: horizontal FoV, degrees.
        episodes_per_image: K >= 0.
        seed: episode seed (``dataset.episode_seed``).
        pitch_bound, max_steps, hard_rule: the sampling rules (docs/TASK.md, Difficulties).

    Returns:
        ``len(difficulties) * len(images) * K`` episodes, difficulty-major, then image, then k.
    """
    fov = check_fov(fov)
    pitch_bound = check_pitch_bound(pitch_bound)
    hard_rule = check_hard_rule(hard_rule)
    if isinstance(episodes_per_image, bool) or int(episodes_per_image) != episodes_per_image or episodes_per_image < 0:
        raise DatasetError(f"episodes_per_image must be an integer >= 0, got {episodes_per_image!r}")
    k_per = int(episodes_per_image)
    split_code = SPLITS.index(split) if split in SPLITS else derive_seed(split)
    tag = fov_tag(fov)
    episodes: list[Episode] = []
    for d in difficulties:
        rng = np.random.default_rng(
            [int(seed), split_code, int(round(fov * 1000)), DIFFICULTIES.index(d), 0x46565354]
        )
        rot = sample_rotations(d, len(images) * k_per, rng, fov, pitch_bound, max_steps, hard_rule, max_tries)
        for i, im in enumerate(images):
            for k in range(k_per):
                r = rot[i * k_per + k]
                eid = f"{split}-fov{tag}-{d}-{i:06d}-{k}"
                episodes.append(
                    Episode(
                        episode_id=eid,
                        image=im.path,
                        init_pitch=int(r[0]),
                        init_yaw=int(r[1]),
                        target_pitch=int(r[2]),
                        target_yaw=int(r[3]),
                        difficulty=d,
                        label=im.label,
                        seed=derive_seed("static", int(seed), split, tag, eid),
                    )
                )
    return episodes


def write_episode_file(
    path: str | os.PathLike,
    episodes: Sequence[Episode],
    *,
    dataset: str,
    root: str | os.PathLike,
    split: str,
    fov: float,
    hard_rule: str,
    seed: int,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write an episode file atomically (header, then one episode per line; images relative to ``root``)."""
    root = os.path.abspath(root)
    header: dict[str, Any] = {
        "dataset": dataset,
        "root": root,
        "split": split,
        "fov": _fov_json(fov),
        "hard_rule": hard_rule,
        "seed": int(seed),
    }
    header.update(extra or {})
    header["count"] = len(episodes)
    lines = ["{"]
    for key, value in header.items():
        lines.append(f" {json.dumps(key)}: {json.dumps(value, sort_keys=True)},")
    body = []
    for ep in episodes:
        d = ep.to_dict()
        d["image"] = relative_image_path(ep.image, root)
        body.append("  " + json.dumps(d))
    if body:
        lines.append(' "episodes": [')
        lines.append(",\n".join(body))
        lines.append(" ]")
    else:
        lines.append(' "episodes": []')
    lines.append("}")
    return write_text(path, "\n".join(lines) + "\n")


def read_episode_file(path: str | os.PathLike) -> dict[str, Any]:
    """The raw episode-file document (error naming the file and how to make it when missing)."""
    path = Path(path)
    hint = (
        f"Make it with: python tools/make_dataset.py dataset=<name> [dataset.root=<folder>] "
        f"(dataset.episode_fovs must include the FoV, dataset.splits_to_make the split)"
    )
    doc = read_json(path, "episode file", hint)
    if not isinstance(doc, dict) or "episodes" not in doc:
        raise DatasetError(f"{path} is not a findview episode file (no 'episodes'). {MAKE_DATASET_HINT}")
    return doc


def load_episodes(path: str | os.PathLike, root: str | os.PathLike | None = None) -> list[Episode]:
    """Episodes of a static episode file, with absolute image paths.

    Args:
        path: an ``episodes/<split>_fov<F>.json`` file.
        root: overrides the dataset root recorded in the file (relative image paths are joined to it).
    """
    doc = read_episode_file(path)
    base = os.path.abspath(os.path.expanduser(root)) if root is not None else str(doc.get("root", ""))
    out = []
    for d in doc["episodes"]:
        ep = Episode.from_dict(d)
        image = ep.image if os.path.isabs(ep.image) else os.path.normpath(os.path.join(base, ep.image))
        out.append(dataclasses.replace(ep, image=image))
    return out
