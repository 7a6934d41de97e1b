"""Finding panoramas on disk (SUN360, 360-Indoor, any folder) and validating them.

Layouts (docs/TASK.md, Datasets and splits):

- ``sun360``: ``<root>/<indoor|outdoor|others>/<sub-category>/pano_*.jpg``. ``subset`` picks
  ``indoor``, ``outdoor``, ``others``, ``all`` or a ``+``-joined list such as ``indoor+outdoor``
  (:func:`sun360_parts`; such a list is split part by part, see :mod:`findview.dataset.prepare`). The label
  is the sub-category (the first folder below ``indoor/`` or ``outdoor/``); every image under ``others/``
  (flat or in sub-folders) is labelled ``"others"``; an image lying directly in ``indoor/`` or ``outdoor/`` is labelled with that name.
- ``indoor360``: a flat folder of panoramas (searched recursively), label ``"indoor360"``.
- ``folder``: any folder, searched recursively; the label is the image's parent folder relative to the
  root (POSIX form, e.g. ``"kitchen"`` or ``"a/b"``), and the root folder's own name for images lying
  directly in the root.

Images are the files whose extension (case-insensitive) is in
:data:`findview.imageio.IMAGE_EXTENSIONS`; hidden files and folders (name starting with ``.``) are
skipped. Discovery only lists files; :func:`validate_images` decodes each one with
:func:`findview.imageio.load_panorama` (readable, not truncated, RGB-convertible, width = 2 x height).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

from findview.imageio import IMAGE_EXTENSIONS, PanoramaError, load_panorama

__all__ = [
    "DatasetError",
    "ImageEntry",
    "KINDS",
    "SUN360_SUBSETS",
    "sun360_parts",
    "SUN360_LAYOUT",
    "discover",
    "discover_sun360",
    "discover_indoor360",
    "discover_folder",
    "validate_images",
]

KINDS = ("sun360", "indoor360", "folder", "synthetic")
SUN360_SUBSETS = ("indoor", "outdoor", "others", "all")
SUN360_LAYOUT = "<root>/<indoor|outdoor|others>/<sub-category>/pano_*.jpg"


class DatasetError(ValueError):
    """A dataset that cannot be used: missing or empty folder, bad config, missing split file..."""


@dataclass(frozen=True, order=True)
class ImageEntry:
    """One panorama of a dataset: its absolute ``path`` and its ``label`` (sub-category)."""

    path: str
    label: str


def _is_image(name: str) -> bool:
    return not name.startswith(".") and os.path.splitext(name)[1].lower() in IMAGE_EXTENSIONS


def _walk_images(folder: Path) -> list[Path]:
    """All image files below ``folder`` (recursive, symlinks followed, hidden entries skipped), sorted."""
    found: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(folder, followlinks=True):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        found.extend(Path(dirpath) / f for f in filenames if _is_image(f))
    return sorted(found)


def _check_folder(folder: Path, what: str, expected: str) -> Path:
    if not folder.exists():
        raise DatasetError(f"{what} folder not found: {folder} (expected {expected})")
    if not folder.is_dir():
        raise DatasetError(f"{what} path is not a folder: {folder} (expected {expected})")
    return folder


def _ext_list() -> str:
    return "/".join(e.lstrip(".") for e in IMAGE_EXTENSIONS)


def sun360_parts(subset: str) -> tuple[str, ...]:
    """The SUN360 folders a ``subset`` names: ``("indoor",)`` for ``indoor``, ``("indoor", "outdoor")`` for
    ``indoor+outdoor``; ``all`` stays ``("all",)`` (one joint split of the three folders).

    Raises:
        DatasetError: an unknown name, ``all`` in a list, or a folder named twice.
    """
    if subset in SUN360_SUBSETS:
        return (subset,)
    parts = tuple(str(subset).split("+"))
    ok = {"indoor", "outdoor", "others"}
    if len(parts) < 2 or any(p not in ok for p in parts) or len(set(parts)) != len(parts):
        raise DatasetError(
            f"unknown SUN360 subset {subset!r}; valid: {', '.join(SUN360_SUBSETS)}, or several of indoor, outdoor "
            f"and others joined by '+' (each once), e.g. indoor+outdoor"
        )
    return parts


def discover_sun360(root: str | os.PathLike, subset: str = "indoor") -> list[ImageEntry]:
    """List the panoramas of a SUN360 copy laid out as :data:`SUN360_LAYOUT`.

    Args:
        root: the folder holding ``indoor/``, ``outdoor/`` and ``others/``.
        subset: ``indoor``, ``outdoor``, ``others``, ``all`` or a ``+``-joined list (:func:`sun360_parts`).

    Returns:
        Entries sorted by path, labels = sub-category (``"others"`` for the ``others`` folder).

    Raises:
        DatasetError: unknown subset, missing root / subset folder, or no image found.
    """
    parts = sun360_parts(subset)
    root = _check_folder(Path(root).expanduser().resolve(), "SUN360 root", f"the SUN360 layout {SUN360_LAYOUT}")
    parts = ("indoor", "outdoor", "others") if parts == ("all",) else parts
    present = [p for p in parts if (root / p).is_dir()]
    if not present:
        missing = root / parts[0] if len(parts) == 1 else root
        raise DatasetError(
            f"SUN360 {subset} folder not found: {missing} (expected the SUN360 layout {SUN360_LAYOUT}; "
            f"dataset.root must be the folder that holds indoor/, outdoor/ and others/)"
        )
    entries: list[ImageEntry] = []
    for part in present:
        base = root / part
        for f in _walk_images(base):
            rel = f.relative_to(base).parts
            label = "others" if part == "others" or len(rel) == 1 else rel[0]
            entries.append(ImageEntry(str(f), label))
    if not entries:
        where = ", ".join(str(root / p) for p in present)
        raise DatasetError(
            f"no panorama found in {where} (expected the SUN360 layout {SUN360_LAYOUT}, "
            f"image extensions {_ext_list()})"
        )
    return sorted(entries)


def discover_indoor360(root: str | os.PathLike) -> list[ImageEntry]:
    """List the panoramas of a 360-Indoor copy (a flat folder of jpgs; searched recursively).

    Returns entries sorted by path, all labelled ``"indoor360"``. Raises :class:`DatasetError` when the
    folder is missing or holds no image.
    """
    root = _check_folder(Path(root).expanduser().resolve(), "360-Indoor", "a folder of equirectangular jpgs")
    entries = [ImageEntry(str(f), "indoor360") for f in _walk_images(root)]
    if not entries:
        raise DatasetError(f"no panorama found in 360-Indoor folder {root} (expected {_ext_list()} images)")
    return entries


def discover_folder(root: str | os.PathLike) -> list[ImageEntry]:
    """List every image below ``root`` (recursive); label = parent folder relative to ``root``.

    Images lying directly in ``root`` get the root folder's name as label. Raises
    :class:`DatasetError` when the folder is missing or holds no image.
    """
    root = _check_folder(Path(root).expanduser().resolve(), "image", "a folder of equirectangular images")
    entries = []
    for f in _walk_images(root):
        parent = f.parent.relative_to(root).as_posix()
        entries.append(ImageEntry(str(f), root.name if parent in ("", ".") else parent))
    if not entries:
        raise DatasetError(
            f"no image found in folder {root} (searched recursively for {_ext_list()} files)"
        )
    return entries


def discover(kind: str, root: str | os.PathLike, subset: str | None = None) -> list[ImageEntry]:
    """Dispatch on ``kind`` (``sun360`` | ``indoor360`` | ``folder``; ``synthetic`` lists a folder)."""
    if kind == "sun360":
        return discover_sun360(root, subset or "indoor")
    if kind == "indoor360":
        return discover_indoor360(root)
    if kind in ("folder", "synthetic"):
        return discover_folder(root)
    raise DatasetError(f"unknown dataset kind {kind!r}; valid: {', '.join(KINDS)}")


def _check_one(path: str) -> str | None:
    try:
        load_panorama(path)
    except PanoramaError as e:
        return str(e)
    except Exception as e:  # pragma: no cover - defensive: any decoder failure names the file
        return f"{path}: {type(e).__name__}: {e}"
    return None


def validate_images(
    entries: Sequence[ImageEntry] | Iterable[ImageEntry],
    workers: int | None = None,
    progress: bool = True,
    max_reported: int = 5,
) -> None:
    """Decode every panorama with :func:`findview.imageio.load_panorama` (threads; OpenCV frees the GIL).

    Args:
        entries: the images to check.
        workers: decoding threads (default ``min(4, cpu_count)``).
        progress: show a tqdm progress bar (stderr).
        max_reported: how many bad files the error message lists.

    Raises:
        PanoramaError: one or more files are unusable; the message names each bad file (up to
            ``max_reported``, then a count).
    """
    paths = [e.path for e in entries]
    if not paths:
        return
    workers = max(1, workers or min(4, os.cpu_count() or 1))
    errors: list[str] = []
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(paths), desc="validating panoramas", unit="img", leave=False)
    else:
        bar = None
    try:
        if workers == 1 or len(paths) < 4:
            results = map(_check_one, paths)
            for err in results:
                if err:
                    errors.append(err)
                if bar is not None:
                    bar.update(1)
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                for err in pool.map(_check_one, paths):
                    if err:
                        errors.append(err)
                    if bar is not None:
                        bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    if errors:
        shown = "; ".join(errors[:max_reported])
        more = f" (and {len(errors) - max_reported} more)" if len(errors) > max_reported else ""
        prefix = "invalid panorama" if len(errors) == 1 else f"{len(errors)} invalid panoramas"
        raise PanoramaError(f"{prefix}: {shown}{more}")
