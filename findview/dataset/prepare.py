"""Build (or reuse) a data set's split file and static episode files from a ``dataset`` config.

:func:`prepare_dataset` is what ``tools/make_dataset.py`` runs; :func:`ensure_dataset` is what train /
eval call so that the quick start works on a fresh machine. The config keys (``configs/dataset/*.yaml``):

==================== ==============================================================================
``name``             data set name (``splits.json`` ``dataset`` field); default: ``kind``
``kind``             ``sun360`` | ``indoor360`` | ``folder`` | ``synthetic``
``root``             image folder (relative paths resolve against the current directory)
``subset``           sun360 only: ``indoor`` | ``outdoor`` | ``others`` | ``all``
``out_dir``          where ``splits.json`` and ``episodes/`` go; default ``data/<name>``
``split``            ``[train, val, test]`` ratios, default ``[0.8, 0.1, 0.1]``
``split_seed``       split seed (default 0)
``episodes_per_image``  K static episodes per image per difficulty (default 1)
``episode_seed``     static episode seed (default 0)
``episode_fovs``     FoVs (degrees) with episode files (default ``[90, 60]``)
``hard_rule``        ``or`` (default) | ``and``
``splits_to_make``   splits with static episode files (default ``[val, test]``)
``validate``         decode every image when (re)building the splits (default true)
``num_images``, ``seed``, ``width``, ``labels``   synthetic only (see :mod:`findview.dataset.synthetic`)
==================== ==============================================================================

Reuse: ``splits.json`` stores a fingerprint of the split-relevant settings (kind, absolute root, subset,
ratios, split seed, synthetic parameters); each episode file stores a fingerprint of that plus its own
settings (split, FoV, K, episode seed, hard rule, pitch bound, max steps). A file whose fingerprint
matches is reused, anything else is rebuilt. Adding images to a folder does not change the fingerprint:
run ``tools/make_dataset.py`` (which always rebuilds) after changing the images.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from findview.dataset.difficulty import check_fov, check_hard_rule, check_pitch_bound
from findview.dataset.discovery import KINDS, DatasetError, ImageEntry, discover, validate_images
from findview.dataset.episodes import episode_file, make_static_episodes, write_episode_file
from findview.dataset.splits import SPLITS, SPLITS_FILE, load_split, normalize_ratios, read_splits, split_entries, write_splits
from findview.dataset.synthetic import GENERATOR_VERSION, SCENE_KINDS, ensure_synthetic_images
from findview.episode import DIFFICULTIES

__all__ = ["DatasetSummary", "dataset_settings", "prepare_dataset", "ensure_dataset", "resolve_path"]

_EPISODE_FORMAT = 1
_ENV_HINT = {"sun360": "SUN360_ROOT", "indoor360": "INDOOR360_ROOT"}
_ROOT_HINT = {
    "sun360": "your SUN360 folder (the one holding indoor/, outdoor/ and others/)",
    "indoor360": "your 360-Indoor folder of panoramas",
    "folder": "a folder of equirectangular images",
    "synthetic": "the folder for the generated images",
}


def resolve_path(path: str | os.PathLike) -> Path:
    """Absolute path; relative paths resolve against the current directory (Hydra 1.3 does not chdir)."""
    return Path(os.path.abspath(os.path.expanduser(str(path))))


def _to_plain(cfg: Any) -> dict[str, Any]:
    """A plain dict of the config, resolving interpolations; a missing mandatory root becomes ``None``."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover
        DictConfig = ListConfig = ()  # type: ignore[assignment,misc]
    if isinstance(cfg, DictConfig):
        out = {}
        for key in cfg.keys():
            if OmegaConf.is_missing(cfg, key):
                out[key] = None
                continue
            value = cfg[key]
            out[key] = OmegaConf.to_container(value, resolve=True) if isinstance(value, (DictConfig, ListConfig)) else value
        return out
    if isinstance(cfg, Mapping):
        return dict(cfg)
    raise DatasetError(f"dataset config must be a mapping, got {type(cfg).__name__}")


def dataset_settings(cfg: Any) -> dict[str, Any]:
    """Validated settings (plain dict with defaults) from a ``dataset`` config (DictConfig or dict)."""
    raw = _to_plain(cfg)
    kind = raw.get("kind")
    if kind not in KINDS:
        raise DatasetError(f"dataset.kind must be one of {', '.join(KINDS)}, got {kind!r}")
    name = str(raw.get("name") or kind)
    root = raw.get("root")
    if root in (None, "", "???"):
        env = _ENV_HINT.get(kind)
        raise DatasetError(
            f"dataset.root is not set for dataset {name!r}: pass dataset.root=<{_ROOT_HINT[kind]}>"
            + (f" or set the environment variable {env}" if env else "")
        )
    st: dict[str, Any] = {
        "name": name,
        "kind": kind,
        "root": str(root),
        "subset": raw.get("subset") or ("indoor" if kind == "sun360" else None),
        "out_dir": str(raw.get("out_dir") or f"data/{name}"),
        "split": list(raw.get("split") if raw.get("split") is not None else (0.8, 0.1, 0.1)),
        "split_seed": int(raw.get("split_seed") or 0),
        "episodes_per_image": raw.get("episodes_per_image", 1),
        "episode_seed": int(raw.get("episode_seed") or 0),
        "episode_fovs": list(raw.get("episode_fovs") if raw.get("episode_fovs") is not None else (90, 60)),
        "hard_rule": check_hard_rule(raw.get("hard_rule") or "or"),
        "splits_to_make": list(raw.get("splits_to_make") if raw.get("splits_to_make") is not None else ("val", "test")),
        "validate": bool(raw.get("validate", True)),
        "workers": raw.get("workers"),
    }
    normalize_ratios(st["split"])
    k = st["episodes_per_image"]
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise DatasetError(f"dataset.episodes_per_image must be an integer >= 0, got {k!r}")
    bad = [s for s in st["splits_to_make"] if s not in SPLITS]
    if bad:
        raise DatasetError(f"dataset.splits_to_make holds unknown splits {bad}; valid: {', '.join(SPLITS)}")
    for f in st["episode_fovs"]:
        check_fov(f)
    if kind == "synthetic":
        st["num_images"] = int(raw.get("num_images") or 40)
        st["seed"] = int(raw.get("seed") or 0)
        st["width"] = int(raw.get("width") or 1024)
        st["labels"] = [str(x) for x in (raw.get("labels") or SCENE_KINDS)]
    return st


def _digest(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode("utf-8")).hexdigest()[:16]


def _splits_fingerprint(st: dict[str, Any], root: Path) -> str:
    key = {
        "kind": st["kind"],
        "root": str(root),
        "subset": st["subset"] if st["kind"] == "sun360" else None,
        "ratios": [float(r) for r in normalize_ratios(st["split"])],
        "split_seed": st["split_seed"],
    }
    if st["kind"] == "synthetic":
        key["synthetic"] = {k: st[k] for k in ("num_images", "seed", "width", "labels")}
        key["synthetic"]["version"] = GENERATOR_VERSION
    return _digest(key)


def _read_episode_header(path: Path) -> dict[str, Any] | None:
    """The header keys of an episode file written by :func:`write_episode_file` (without parsing the
    episodes); ``None`` when unreadable."""
    try:
        lines = []
        with open(path) as f:
            first = f.readline()
            if first.strip() != "{":
                return None
            for line in f:
                if line.startswith(' "episodes"'):
                    break
                lines.append(line)
        return json.loads("{" + "".join(lines).rstrip().rstrip(",") + "}")
    except (OSError, ValueError):
        return None


@dataclass
class DatasetSummary:
    """What :func:`prepare_dataset` produced or reused."""

    name: str
    kind: str
    root: Path
    out_dir: Path
    splits_file: Path
    splits_reused: bool
    images: dict[str, int]
    labels: dict[str, dict[str, int]]
    episode_files: dict[tuple[str, float], Path] = field(default_factory=dict)
    episode_counts: dict[tuple[str, float], dict[str, int]] = field(default_factory=dict)
    episodes_reused: dict[tuple[str, float], bool] = field(default_factory=dict)

    def format(self) -> str:
        """A human-readable multi-line summary."""
        lines = [f"dataset {self.name} ({self.kind}), images from {self.root}"]
        state = "reused" if self.splits_reused else "written"
        lines.append(f"splits ({state}): {self.splits_file}")
        for s in SPLITS:
            labels = ", ".join(f"{k}: {v}" for k, v in sorted(self.labels.get(s, {}).items()))
            lines.append(f"  {s:5s} {self.images.get(s, 0):6d} images" + (f"  ({labels})" if labels else ""))
        if self.episode_files:
            fovs = sorted({f for _, f in self.episode_files})
            lines.append("episodes (FoVs " + ", ".join(f"{f:g}" for f in fovs) + "):")
            for key, path in self.episode_files.items():
                counts = self.episode_counts.get(key, {})
                per = ", ".join(f"{d} {counts.get(d, 0)}" for d in DIFFICULTIES)
                state = "reused" if self.episodes_reused.get(key) else "written"
                lines.append(f"  {key[0]:5s} fov {key[1]:g}: {sum(counts.values()):6d} episodes ({per}) -> {path} ({state})")
                if not counts or sum(counts.values()) == 0:
                    lines.append(f"  warning: {path.name} holds no episode (empty split or episodes_per_image=0)")
        return "\n".join(lines)


def prepare_dataset(
    dataset_cfg: Any,
    fovs: Iterable[float] | None = None,
    *,
    pitch_bound: int = 60,
    max_steps: int = 5000,
    force: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> DatasetSummary:
    """Make ``splits.json`` and the static episode files of ``dataset_cfg`` (reusing matching ones).

    Args:
        dataset_cfg: a ``dataset`` config node or dict (keys in the module docstring).
        fovs: FoVs (degrees) to make episode files for; ``None`` = ``dataset.episode_fovs``.
        pitch_bound: pitch bound of the sampled rotations (``task.pitch_bound``), degrees.
        max_steps: T (``task.max_steps``); episodes have ``10 < L1 < T``.
        force: rebuild everything (images are still only generated when missing / changed).
        progress: tqdm progress bars.
        log: where to report progress lines (default: silent).

    Raises:
        DatasetError, PanoramaError, SamplingError, FileNotFoundError: with messages naming the file,
        folder or setting at fault.
    """
    st = dataset_settings(dataset_cfg)
    fov_list = [check_fov(f) for f in (st["episode_fovs"] if fovs is None else fovs)]
    fov_list = list(dict.fromkeys(fov_list))
    pitch_bound = check_pitch_bound(pitch_bound)
    say = log or (lambda msg: None)
    root = resolve_path(st["root"])
    out_dir = resolve_path(st["out_dir"])
    fp = _splits_fingerprint(st, root)
    entries: list[ImageEntry] | None = None
    if st["kind"] == "synthetic":
        say(f"synthetic images under {root}")
        entries = ensure_synthetic_images(
            root, st["num_images"], st["seed"], st["width"], st["labels"], progress, workers=st["workers"]
        )

    splits_path = out_dir / SPLITS_FILE
    reused = False
    splits: dict[str, list[ImageEntry]]
    if not force and splits_path.is_file():
        try:
            doc = read_splits(out_dir)
            reused = doc.get("fingerprint") == fp
        except (ValueError, OSError):
            reused = False
    if reused:
        splits = {s: load_split(out_dir, s) for s in SPLITS}
        say(f"reusing {splits_path}")
    else:
        if entries is None:
            entries = discover(st["kind"], root, st["subset"])
        say(f"found {len(entries)} images under {root}")
        if st["validate"]:
            validate_images(entries, workers=st["workers"], progress=progress)
        splits = split_entries(entries, root, st["split"], st["split_seed"])
        extra = {"kind": st["kind"], "subset": st["subset"], "fingerprint": fp}
        write_splits(out_dir, splits, dataset=st["name"], root=root, seed=st["split_seed"], ratios=st["split"], extra=extra)
        say(f"wrote {splits_path}")

    labels = {s: {} for s in SPLITS}
    for s in SPLITS:
        for e in splits[s]:
            labels[s][e.label] = labels[s].get(e.label, 0) + 1
    summary = DatasetSummary(
        name=st["name"], kind=st["kind"], root=root, out_dir=out_dir, splits_file=splits_path,
        splits_reused=reused, images={s: len(splits[s]) for s in SPLITS}, labels=labels,
    )
    K = st["episodes_per_image"]
    for split in st["splits_to_make"]:
        for fov in fov_list:
            path = episode_file(out_dir, split, fov)
            efp = _digest({
                "splits": fp, "split": split, "fov": fov, "K": K, "seed": st["episode_seed"],
                "hard_rule": st["hard_rule"], "pitch_bound": pitch_bound, "max_steps": int(max_steps),
                "format": _EPISODE_FORMAT,
            })
            header = None if force or not reused or not path.is_file() else _read_episode_header(path)
            key = (split, fov)
            summary.episode_files[key] = path
            if header is not None and header.get("fingerprint") == efp:
                summary.episode_counts[key] = dict(header.get("difficulty_counts", {}))
                summary.episodes_reused[key] = True
                continue
            episodes = make_static_episodes(
                splits[split], split, fov, K, st["episode_seed"], pitch_bound, max_steps, st["hard_rule"]
            )
            counts = {d: sum(1 for e in episodes if e.difficulty == d) for d in DIFFICULTIES}
            write_episode_file(
                path, episodes, dataset=st["name"], root=root, split=split, fov=fov, hard_rule=st["hard_rule"],
                seed=st["episode_seed"],
                extra={"episodes_per_image": K, "pitch_bound": pitch_bound, "max_steps": int(max_steps),
                       "fingerprint": efp, "difficulty_counts": counts},
            )
            summary.episode_counts[key] = counts
            summary.episodes_reused[key] = False
            say(f"wrote {path}")
    return summary


def ensure_dataset(
    dataset_cfg: Any,
    fovs: Iterable[float] | None = None,
    *,
    pitch_bound: int = 60,
    max_steps: int = 5000,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> Path:
    """Make sure ``splits.json`` and the val/test episode files for ``fovs`` exist and match the config
    (building them, and the synthetic images, when missing or stale); returns the absolute ``out_dir``.

    Train / eval call this with ``cfg.dataset`` and ``[cfg.sim.fov]`` (and ``task.pitch_bound`` /
    ``task.max_steps``), then read files with :func:`findview.dataset.episode_file` /
    :func:`findview.dataset.load_episodes` / :func:`findview.dataset.load_split`.
    """
    return prepare_dataset(
        dataset_cfg, fovs, pitch_bound=pitch_bound, max_steps=max_steps, force=False, progress=progress, log=log
    ).out_dir
