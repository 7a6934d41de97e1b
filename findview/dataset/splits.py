"""Deterministic train/val/test splits per sub-category, stored as ``<out_dir>/splits.json``.

The rule (docs/TASK.md, Datasets and splits), identical on every machine:

1. Images are grouped by label (sub-category); labels are processed in sorted order.
2. Within a label, images are ordered by ``sha256("<seed>/<label>/<path relative to root>")`` -- a
   seeded shuffle that depends only on the file names, never on the file system order, the platform or
   the numpy version.
3. Counts: with normalised ratios ``r = (r_train, r_val, r_test)`` and ``n`` images in the label, each
   split gets ``floor(n * r_s)`` images (exact rational arithmetic), and the ``n - sum(floor)`` leftover
   images go, one each, to the splits with a non-zero fractional quota ``n * r_s - floor(n * r_s)``,
   preferring the split that is furthest below its share of the whole dataset so far (cumulative
   deficit ``r_s * N_seen - assigned_s``), ties by split order train, val, test. So every label is
   split within one image of its exact quota and the dataset totals stay within one image of theirs;
   a zero ratio never receives an image (``[0, 0, 1]`` puts everything in test).
4. The first ``n_train`` images of the order go to train, the next ``n_val`` to val, the rest to test.
   Each split's list is then sorted by path for readability.

Every image lands in exactly one split.
"""

from __future__ import annotations

import hashlib
import os
from fractions import Fraction
from pathlib import Path
from typing import Any, Sequence

from findview.dataset.discovery import DatasetError, ImageEntry
from findview.utils import read_json, write_json

__all__ = [
    "SPLITS",
    "SPLITS_FILE",
    "normalize_ratios",
    "split_counts",
    "split_entries",
    "relative_image_path",
    "write_splits",
    "read_splits",
    "load_split",
    "MAKE_DATASET_HINT",
    "MissingDataFile",
]

SPLITS = ("train", "val", "test")
SPLITS_FILE = "splits.json"
MAKE_DATASET_HINT = "Make it with: python tools/make_dataset.py dataset=<name> [dataset.root=<folder>]"


class MissingDataFile(FileNotFoundError):
    """A data set file (``splits.json``, an episode file) that does not exist; the message names it and the
    ``tools/make_dataset.py`` command that makes it (a user error: the tools print it as one line)."""


def normalize_ratios(ratios: Sequence[float]) -> tuple[Fraction, Fraction, Fraction]:
    """Validate 3 non-negative ratios with a positive sum and return them normalised, as exact fractions.

    Each ratio is read through its decimal string (``0.1`` is exactly 1/10).
    """
    ratios = list(ratios)
    if len(ratios) != 3:
        raise DatasetError(f"dataset.split must hold 3 ratios [train, val, test], got {ratios}")
    try:
        fr = [Fraction(str(float(r))) for r in ratios]
    except (TypeError, ValueError) as e:
        raise DatasetError(f"dataset.split must hold 3 numbers, got {ratios}") from e
    if any(r < 0 for r in fr) or sum(fr) <= 0:
        raise DatasetError(f"dataset.split ratios must be >= 0 with a positive sum, got {ratios}")
    total = sum(fr)
    return tuple(r / total for r in fr)  # type: ignore[return-value]


def split_counts(
    n: int, ratios: Sequence[Fraction], assigned: list[int] | None = None, seen: int = 0
) -> list[int]:
    """Images per split for one label of ``n`` images (rule 3 in the module docstring).

    ``assigned`` (running totals per split over the labels already processed) and ``seen`` (images in
    those labels) steer the leftovers towards the splits furthest below their dataset-wide share.
    """
    assigned = assigned or [0, 0, 0]
    quotas = [n * r for r in ratios]
    base = [int(q) for q in quotas]  # floor: quotas are non-negative
    left = n - sum(base)
    candidates = [s for s in range(3) if quotas[s] - base[s] > 0]
    total_seen = seen + n

    def key(s: int) -> tuple:
        deficit = ratios[s] * total_seen - (assigned[s] + base[s])
        return (-deficit, s)

    for s in sorted(candidates, key=key)[:left]:
        base[s] += 1
    return base


def relative_image_path(path: str | os.PathLike, root: str | os.PathLike) -> str:
    """``path`` relative to ``root`` in POSIX form (``..`` allowed when outside the root)."""
    return Path(os.path.relpath(os.path.abspath(path), os.path.abspath(root))).as_posix()


def _order_key(seed: int, label: str, rel: str) -> str:
    return hashlib.sha256(f"{seed}/{label}/{rel}".encode("utf-8")).hexdigest()


def split_entries(
    entries: Sequence[ImageEntry],
    root: str | os.PathLike,
    ratios: Sequence[float] = (0.8, 0.1, 0.1),
    seed: int = 0,
) -> dict[str, list[ImageEntry]]:
    """Split ``entries`` 80/10/10 (or ``ratios``) within each label, deterministically.

    Args:
        entries: the dataset's images (absolute paths).
        root: dataset root; the shuffle hashes paths relative to it, so the split does not depend on
            where the dataset lives.
        ratios: ``[train, val, test]`` shares (normalised).
        seed: split seed.

    Returns:
        ``{"train": [...], "val": [...], "test": [...]}``, each sorted by path.
    """
    fr = normalize_ratios(ratios)
    seen_paths: set[str] = set()
    by_label: dict[str, list[tuple[str, ImageEntry]]] = {}
    for e in entries:
        if e.path in seen_paths:
            raise DatasetError(f"duplicate image in dataset: {e.path}")
        seen_paths.add(e.path)
        by_label.setdefault(e.label, []).append((relative_image_path(e.path, root), e))
    out: dict[str, list[ImageEntry]] = {s: [] for s in SPLITS}
    assigned = [0, 0, 0]
    seen = 0
    for label in sorted(by_label):
        items = sorted(by_label[label], key=lambda it: (_order_key(seed, label, it[0]), it[0]))
        counts = split_counts(len(items), fr, assigned, seen)
        start = 0
        for s, c in enumerate(counts):
            out[SPLITS[s]].extend(e for _, e in items[start : start + c])
            start += c
            assigned[s] += c
        seen += len(items)
    for s in SPLITS:
        out[s].sort()
    return out


def write_splits(
    out_dir: str | os.PathLike,
    splits: dict[str, list[ImageEntry]],
    *,
    dataset: str,
    root: str | os.PathLike,
    seed: int,
    ratios: Sequence[float],
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``<out_dir>/splits.json`` atomically (schema in docs/ARCHITECTURE.md).

    Image paths are stored relative to ``root``; ``extra`` adds header keys (kind, fingerprint...).
    """
    root = Path(os.path.abspath(root))
    doc: dict[str, Any] = {
        "dataset": dataset,
        "root": str(root),
        "seed": int(seed),
        "ratios": [float(r) for r in normalize_ratios(ratios)],
    }
    doc.update(extra or {})
    doc["counts"] = {s: len(splits.get(s, [])) for s in SPLITS}
    doc["splits"] = {
        s: [{"image": relative_image_path(e.path, root), "label": e.label} for e in splits.get(s, [])]
        for s in SPLITS
    }
    return write_json(Path(out_dir) / SPLITS_FILE, doc)


def read_splits(out_dir: str | os.PathLike) -> dict[str, Any]:
    """The raw ``splits.json`` document of ``out_dir`` (clear error when missing)."""
    path = Path(out_dir) / SPLITS_FILE
    try:
        doc = read_json(path, "splits file", MAKE_DATASET_HINT)
    except FileNotFoundError as err:
        raise MissingDataFile(str(err)) from None
    except ValueError as err:
        raise DatasetError(f"{err}. {MAKE_DATASET_HINT}") from None
    if not isinstance(doc, dict) or "splits" not in doc or "root" not in doc:
        raise DatasetError(f"{path} is not a findview splits file (missing 'splits' or 'root'). {MAKE_DATASET_HINT}")
    return doc


def load_split(out_dir: str | os.PathLike, split: str, root: str | os.PathLike | None = None) -> list[ImageEntry]:
    """The images of ``split`` (``train`` | ``val`` | ``test``) from ``<out_dir>/splits.json``.

    Args:
        out_dir: the dataset output folder.
        split: split name.
        root: overrides the dataset root recorded in the file (e.g. a shared splits file used on another
            machine).

    Returns:
        Entries with absolute image paths, in file order.
    """
    if split not in SPLITS:
        raise DatasetError(f"unknown split {split!r}; valid: {', '.join(SPLITS)}")
    doc = read_splits(out_dir)
    base = Path(os.path.abspath(Path(root).expanduser())) if root is not None else Path(doc["root"])
    items = doc["splits"].get(split, [])
    return [ImageEntry(os.path.normpath(base / it["image"]), str(it.get("label", ""))) for it in items]
