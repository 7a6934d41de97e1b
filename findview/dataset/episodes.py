"""Static (val / test) episode files: ``<out_dir>/episodes/<split>_fov<F:g>.json``.

For a split, a FoV ``F`` and ``K = episodes_per_image``, the file holds, for each difficulty in
``easy, medium, hard`` (in that order), for each image of the split (in ``splits.json`` order), ``K``
episodes. The rotations of the ``k``-th episode of every image come from one call of
:func:`findview.dataset.sampler.sample_rotations` (one rotation per image, in image order) with a
generator seeded by ``(seed, split, F, difficulty)`` for ``k = 0`` and ``(seed, split, F, difficulty, k)``
for ``k > 0``, so the same inputs always give a byte-identical file, and the first ``k`` episodes per
image per difficulty of a file made with ``K >= k`` are exactly the file made with ``k`` (same ids,
seeds and rotations): tools that need fewer episodes per image than a file holds take that subset
(:func:`load_episodes` ``episodes_per_image=``; the header's ``nested: true`` marks files made this
way). Files with ``K = 1`` are those of the earlier layout; files with ``K > 1`` made before were
sampled in one stream and are not nested (their fingerprint differs, so they are rebuilt).
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
from findview.dataset.splits import MAKE_DATASET_HINT, SPLITS, MissingDataFile, relative_image_path
from findview.episode import DIFFICULTIES, Episode
from findview.utils import read_json, write_text

__all__ = [
    "episode_file", "episode_index", "fov_tag", "make_static_episodes", "write_episode_file", "load_episodes",
    "read_episode_file",
]


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
        ``len(difficulties) * len(images) * K`` episodes, difficulty-major, then image, then k; the
        episodes with ``k < k'`` are those of ``episodes_per_image=k'`` (module docstring).
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
        base = [int(seed), split_code, int(round(fov * 1000)), DIFFICULTIES.index(d), 0x46565354]
        # one stream per k (k = 0: the stream of the K = 1 files), so that a file's first k episodes per
        # image are the file made with K = k
        rots = [
            sample_rotations(d, len(images), np.random.default_rng(base + ([k] if k else [])), fov, pitch_bound,
                             max_steps, hard_rule, max_tries)
            for k in range(k_per)
        ]
        for i, im in enumerate(images):
            for k in range(k_per):
                r = rots[k][i]
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
        "Make it with: python tools/make_dataset.py dataset=<name> [dataset.root=<folder>] "
        "(dataset.episode_fovs must include the FoV, dataset.splits_to_make the split)"
    )
    try:
        doc = read_json(path, "episode file", hint)
    except FileNotFoundError as err:
        raise MissingDataFile(str(err)) from None
    except ValueError as err:
        raise DatasetError(f"{err}. {MAKE_DATASET_HINT}") from None
    if not isinstance(doc, dict) or "episodes" not in doc:
        raise DatasetError(f"{path} is not a findview episode file (no 'episodes'). {MAKE_DATASET_HINT}")
    return doc


def episode_index(episode_id: str) -> int:
    """The ``k`` of an episode id ``"<split>-fov<F>-<difficulty>-<image index>-<k>"``."""
    try:
        return int(str(episode_id).rsplit("-", 1)[1])
    except (IndexError, ValueError):
        raise DatasetError(f"episode id {episode_id!r} does not end in '-<k>' (not made by tools/make_dataset.py)") from None


def load_episodes(
    path: str | os.PathLike, root: str | os.PathLike | None = None, episodes_per_image: int | None = None
) -> list[Episode]:
    """Episodes of a static episode file, with absolute image paths.

    Args:
        path: an ``episodes/<split>_fov<F>.json`` file.
        root: overrides the dataset root recorded in the file (relative image paths are joined to it).
        episodes_per_image: keep the first ``k`` episodes per image per difficulty (the episodes the file
            made with ``dataset.episodes_per_image=k`` holds, see the module docstring); ``None``: all.

    Raises:
        DatasetError: the file holds fewer than ``episodes_per_image`` episodes per image, or more but
            was not made nested (an older file with ``K > 1``).
    """
    doc = read_episode_file(path)
    keep: int | None = None
    if episodes_per_image is not None:
        have, k = doc.get("episodes_per_image"), int(episodes_per_image)
        nested = have is not None and (doc.get("nested") is True or int(have) <= 1)
        if have is None or (int(have) != k and (int(have) < k or not nested)):
            made = "an unknown number of" if have is None else f"{have}"
            why = "fewer" if have is not None and int(have) < k else "a file whose first episodes are not that subset"
            raise DatasetError(
                f"{path} holds {made} episodes per image per difficulty (dataset.episodes_per_image) but "
                f"{k} are asked for ({why}); make the file with: python tools/make_dataset.py "
                f"dataset=<name> dataset.episodes_per_image={k} plus this run's dataset.* overrides"
            )
        keep = k if int(have) != k else None
    base = os.path.abspath(os.path.expanduser(root)) if root is not None else str(doc.get("root", ""))
    out = []
    for d in doc["episodes"]:
        try:
            ep = Episode.from_dict(d)
        except (KeyError, TypeError, ValueError) as err:
            raise DatasetError(f"{path}: not a findview episode record ({err}). {MAKE_DATASET_HINT}") from None
        if keep is not None and episode_index(ep.episode_id) >= keep:
            continue
        image = ep.image if os.path.isabs(ep.image) else os.path.normpath(os.path.join(base, ep.image))
        out.append(dataclasses.replace(ep, image=image))
    return out
