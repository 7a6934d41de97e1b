"""Build (or reuse) a data set's split file and static episode files from a ``dataset`` config.

:func:`prepare_dataset` is what ``tools/make_dataset.py`` runs; :func:`ensure_dataset` is what train /
eval call so that the quick start works on a fresh machine. Both take the validated ``dataset`` section
(:class:`findview.config.DatasetConfig`: every key, its unit and its default are documented there); the
static episodes follow ``episode_seed``, ``episodes_per_image``, ``episode_fovs``, ``episode_pitch_bound``
(a tool whose ``task.pitch_bound`` differs refuses the files, see :func:`ensure_dataset`),
``episode_max_steps`` (independent of the ``task.max_steps`` a tool runs with) and ``hard_rule``.

The static episode files are a function of the ``dataset`` config alone (never of the ``task`` settings
of the tool that runs; docs/TASK.md, Datasets and splits).

Reuse: ``splits.json`` stores a fingerprint of the split-relevant settings (kind, absolute root, subset,
ratios, split seed, synthetic parameters); each episode file stores a fingerprint of that plus its own
settings (split, FoV, K, episode seed, hard rule, episode pitch bound, episode max steps).
:func:`prepare_dataset` reuses a file whose fingerprint matches and rebuilds anything else;
:func:`ensure_dataset` only writes missing files and raises :class:`DatasetError` (naming the file, the
differing settings and the ``tools/make_dataset.py`` command) instead of overwriting a file made for
other settings, except that an episode file made with more episodes per image than asked for (all else
equal) serves a tool asking for fewer: the tool reads its first ``K`` per image per difficulty, which are
the episodes of the file made with ``K`` (:mod:`findview.dataset.episodes`). Adding images to a folder does not change the fingerprint: run
``tools/make_dataset.py`` (which always rebuilds) after changing the images.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping

from findview.dataset.difficulty import MIN_PATH, check_fov, check_hard_rule, check_pitch_bound
from findview.dataset.discovery import KINDS, DatasetError, ImageEntry, discover, sun360_parts, validate_images
from findview.dataset.episodes import episode_file, make_static_episodes, write_episode_file
from findview.dataset.splits import SPLITS, SPLITS_FILE, load_split, normalize_ratios, read_splits, split_entries, write_splits
from findview.dataset.synthetic import GENERATOR_VERSION, ensure_synthetic_images
from findview.episode import DIFFICULTIES

if TYPE_CHECKING:  # findview.config imports the task, which imports this package
    from findview.config import DatasetConfig

__all__ = ["DatasetSummary", "dataset_settings", "prepare_dataset", "ensure_dataset", "make_dataset_command", "resolve_path"]

_EPISODE_FORMAT = 1
_NESTED_LAYOUT = 2
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


def dataset_settings(cfg: "DatasetConfig") -> dict[str, Any]:
    """The settings record of a ``dataset`` section (a plain dict: fingerprints, file headers and messages
    read it), after the checks the schema's types cannot express.

    Raises:
        DatasetError: no root for the data set, an episode pitch bound or step limit out of range (naming the
            key and the fix).
    """
    kind, name = cfg.kind, cfg.name
    if kind not in KINDS:
        raise DatasetError(f"dataset.kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if cfg.root in (None, ""):
        env = _ENV_HINT.get(kind)
        raise DatasetError(
            f"dataset.root is not set for dataset {name!r}: pass dataset.root=<{_ROOT_HINT[kind]}>"
            + (f" or set the environment variable {env}" if env else "")
        )
    st: dict[str, Any] = {
        "name": name,
        "kind": kind,
        "root": str(cfg.root),
        # a sun360 layout without a subset reads the indoor panoramas (the paper's main data)
        "subset": cfg.subset if cfg.subset is not None or kind != "sun360" else "indoor",
        "out_dir": str(cfg.out_dir),
        "split": list(cfg.split),
        "split_seed": int(cfg.split_seed),
        "episodes_per_image": int(cfg.episodes_per_image),
        "episode_seed": int(cfg.episode_seed),
        "episode_fovs": list(cfg.episode_fovs),
        "episode_pitch_bound": int(cfg.episode_pitch_bound),
        "episode_max_steps": int(cfg.episode_max_steps),
        "hard_rule": cfg.hard_rule,
        "splits_to_make": list(cfg.splits_to_make),
        "validate": bool(cfg.validate),
    }
    normalize_ratios(st["split"])
    try:
        st["hard_rule"] = check_hard_rule(st["hard_rule"])
        for f in st["episode_fovs"]:
            check_fov(f)
    except ValueError as e:
        raise DatasetError(f"dataset: {e}") from None
    bad = [s for s in st["splits_to_make"] if s not in SPLITS]
    if bad:
        raise DatasetError(f"dataset.splits_to_make holds unknown splits {bad}; valid: {', '.join(SPLITS)}")
    try:
        check_pitch_bound(st["episode_pitch_bound"])
    except ValueError as e:
        raise DatasetError(f"dataset.episode_pitch_bound: {e}") from None
    if st["episode_max_steps"] <= MIN_PATH + 1:
        raise DatasetError(
            f"dataset.episode_max_steps must be > {MIN_PATH + 1} steps (episodes need {MIN_PATH} < L1 < T), "
            f"got {st['episode_max_steps']}"
        )
    if kind == "synthetic":
        st.update(num_images=int(cfg.num_images), seed=int(cfg.seed), width=int(cfg.width),
                  labels=[str(x) for x in cfg.labels])
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


def _episodes_fingerprint(splits_fp: str, split: str, fov: float, k: int, st: Mapping[str, Any]) -> str:
    """The fingerprint of an episode file (its split, FoV and ``K`` plus the episode settings of ``st``)."""
    # the digest keys are those of the earlier format, so that files made with the defaults stay valid;
    # K > 1 files are nested since format 1 + layout 2 (findview.dataset.episodes), earlier ones are not
    key = {
        "splits": splits_fp, "split": split, "fov": fov, "K": int(k), "seed": st["episode_seed"],
        "hard_rule": st["hard_rule"], "pitch_bound": st["episode_pitch_bound"], "max_steps": st["episode_max_steps"],
        "format": _EPISODE_FORMAT,
    }
    if int(k) > 1:
        key["layout"] = _NESTED_LAYOUT
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


_KNOWN_CONFIGS = ("synthetic", "sun360_indoor", "sun360_outdoor", "indoor360", "folder")


def make_dataset_command(st: Mapping[str, Any], **overrides: Any) -> str:
    """The ``tools/make_dataset.py`` command line that (re)builds the files of settings ``st`` (plus
    ``dataset.<key>=<value>`` ``overrides``)."""
    name = st["name"]
    args = [f"dataset={name if name in _KNOWN_CONFIGS else st['kind'] if st['kind'] in _KNOWN_CONFIGS else '<config>'}"]
    if name not in _KNOWN_CONFIGS:
        args.append(f"dataset.name={name}")
    if st["kind"] != "synthetic":
        args.append(f"dataset.root={st['root']}")
    for key, value in overrides.items():
        args.append(f"dataset.{key}={value}")
    if "out_dir" not in overrides:
        args.append(f"dataset.out_dir={st['out_dir']}")
    return "python tools/make_dataset.py " + " ".join(args)


def _splits_overrides(doc: Mapping[str, Any], st: Mapping[str, Any], root: Path) -> dict[str, Any]:
    """``dataset.<key>=<value>`` overrides (this run's values) for the split settings recorded differently
    in a ``splits.json`` document, so that the suggested command makes the files this run needs."""
    out: dict[str, Any] = {}
    if doc.get("root") is not None and doc.get("root") != str(root) and st["kind"] == "synthetic":
        out["root"] = st["root"]  # make_dataset_command names the root of the other kinds anyway
    if doc.get("seed") is not None and doc.get("seed") != st["split_seed"]:
        out["split_seed"] = st["split_seed"]
    ratios = [float(r) for r in normalize_ratios(st["split"])]
    if doc.get("ratios") is not None and doc.get("ratios") != ratios:
        out["split"] = "[" + ",".join(f"{float(r):g}" for r in st["split"]) + "]"
    if st["kind"] == "sun360" and doc.get("subset") is not None and doc.get("subset") != st["subset"]:
        out["subset"] = st["subset"]
    return out


def _splits_mismatch(doc: Mapping[str, Any], st: Mapping[str, Any], root: Path) -> str:
    """Which recorded split settings of a ``splits.json`` document differ from ``st`` (for messages)."""
    diffs = []
    recorded = {
        "kind": (doc.get("kind"), st["kind"]),
        "root": (doc.get("root"), str(root)),
        "split_seed": (doc.get("seed"), st["split_seed"]),
        "split": (doc.get("ratios"), [float(r) for r in normalize_ratios(st["split"])]),
    }
    if st["kind"] == "sun360":
        recorded["subset"] = (doc.get("subset"), st["subset"])
    for key, (old, new) in recorded.items():
        if old is not None and old != new:
            diffs.append(f"{key} {old!r} in the file, {new!r} now")
    if not diffs:
        diffs.append("synthetic parameters (num_images, seed, width, labels) or the generator version"
                     if st["kind"] == "synthetic" else "its fingerprint (written by another version?)")
    return "; ".join(diffs)


def _episodes_recorded(header: Mapping[str, Any], st: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    return {
        "episodes_per_image": (header.get("episodes_per_image"), st["episodes_per_image"]),
        "episode_seed": (header.get("seed"), st["episode_seed"]),
        "hard_rule": (header.get("hard_rule"), st["hard_rule"]),
        "episode_pitch_bound": (header.get("pitch_bound"), st["episode_pitch_bound"]),
        "episode_max_steps": (header.get("max_steps"), st["episode_max_steps"]),
    }


def _episodes_mismatch(header: Mapping[str, Any], st: Mapping[str, Any]) -> str:
    """Which episode settings recorded in an episode-file header differ from ``st`` (for messages)."""
    recorded = _episodes_recorded(header, st)
    diffs = [f"dataset.{k} {old!r} in the file, {new!r} now" for k, (old, new) in recorded.items() if old != new]
    return "; ".join(diffs) or "it was made from another splits.json or by another version"


def prepare_dataset(
    dataset_cfg: DatasetConfig,
    fovs: Iterable[float] | None = None,
    *,
    force: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> DatasetSummary:
    """Make ``splits.json`` and the static episode files of ``dataset_cfg`` (reusing matching ones,
    rebuilding the others).

    Args:
        dataset_cfg: the ``dataset`` section (keys in the module docstring). The episodes
            follow ``dataset.episode_*`` and ``dataset.hard_rule`` only (docs/TASK.md, Difficulties).
        fovs: FoVs (degrees) to make episode files for; ``None`` = ``dataset.episode_fovs``.
        force: rebuild everything (images are still only generated when missing / changed).
        progress: tqdm progress bars.
        log: where to report progress lines (default: silent).

    Raises:
        DatasetError, PanoramaError, SamplingError, FileNotFoundError: with messages naming the file,
        folder or setting at fault.
    """
    return _build(dataset_cfg, fovs, force=force, rewrite=True, progress=progress, log=log)


def ensure_dataset(
    dataset_cfg: DatasetConfig,
    fovs: Iterable[float] | None = None,
    *,
    pitch_bound: int | None = None,
    max_steps: int | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    splits: Iterable[str] | None = None,
) -> Path:
    """Make sure ``splits.json`` and the static episode files for ``fovs`` exist and match ``dataset_cfg``;
    returns the absolute ``out_dir``.

    Missing files are made (and the synthetic images generated); existing files are never rewritten, with
    one exception that changes no episode: a nested episode file with fewer episodes per image than
    ``dataset.episodes_per_image`` asks for (all other settings equal) is replaced by the file made with
    ``K``, whose first episodes per image are the ones it held. An episode file made with more episodes per
    image (all other settings equal) is accepted: its first ``K`` episodes per image per difficulty are the
    ones asked for (read them with ``load_episodes(path, episodes_per_image=K)``).
    Train / eval call this with ``cfg.dataset``, ``[cfg.sim.fov]`` and ``pitch_bound=task.pitch_bound``,
    then read the files with :func:`findview.dataset.episode_file` / :func:`findview.dataset.load_episodes`
    / :func:`findview.dataset.load_split`.

    Args:
        dataset_cfg: the ``dataset`` section.
        fovs: FoVs (degrees) whose episode files are needed; ``None`` = ``dataset.episode_fovs``.
        pitch_bound: the caller's pitch clamp (``task.pitch_bound``, degrees). When given and episode
            files are needed, it must equal ``dataset.episode_pitch_bound``: episodes sampled for another
            bound would start or end outside the clamp (or follow another distribution).
        max_steps: ignored, accepted so that callers may pass ``task.max_steps``: the files keep
            ``dataset.episode_max_steps``; with a shorter T, episodes whose path is longer than T end in
            a forced stop.
        progress: tqdm progress bars.
        log: where to report progress lines (default: silent).
        splits: the splits whose episode files are needed (those of ``dataset.splits_to_make`` among them);
            ``None``: all of ``dataset.splits_to_make``.

    Raises:
        DatasetError: ``splits.json`` or an episode file exists but was made for other settings (or with
            fewer episodes per image than asked for), or
            ``pitch_bound`` does not match; a one-line message naming the file, the mismatch and the
            ``tools/make_dataset.py`` command that makes matching files.
    """
    del max_steps  # documented above: the static episodes never depend on the tool's T
    return _build(dataset_cfg, fovs, force=False, rewrite=False, pitch_bound=pitch_bound, progress=progress,
                  log=log, splits=splits).out_dir


def _build(
    dataset_cfg: DatasetConfig,
    fovs: Iterable[float] | None,
    *,
    force: bool,
    rewrite: bool,
    pitch_bound: int | None = None,
    progress: bool,
    log: Callable[[str], None] | None,
    splits: Iterable[str] | None = None,
) -> DatasetSummary:
    """:func:`prepare_dataset` (``rewrite=True``: stale files are rebuilt) and :func:`ensure_dataset`
    (``rewrite=False``: stale files raise)."""
    st = dataset_settings(dataset_cfg)
    fov_list = [check_fov(f) for f in (st["episode_fovs"] if fovs is None else fovs)]
    fov_list = list(dict.fromkeys(fov_list))
    say = log or (lambda msg: None)
    root = resolve_path(st["root"])
    out_dir = resolve_path(st["out_dir"])
    splits_path = out_dir / SPLITS_FILE
    needed = st["splits_to_make"] if splits is None else [s for s in st["splits_to_make"] if s in set(splits)]
    wanted = [(split, fov) for split in needed for fov in fov_list]
    if pitch_bound is not None and wanted:
        _check_episode_pitch_bound(st, int(pitch_bound), episode_file(out_dir, *wanted[0]))
    fp = _splits_fingerprint(st, root)
    reused = _splits_reusable(st, root, out_dir, fp, force, rewrite)
    split_images = _split_images(st, root, out_dir, fp, reused, progress, say)

    labels: dict[str, dict[str, int]] = {s: {} for s in SPLITS}
    for s in SPLITS:
        for e in split_images[s]:
            labels[s][e.label] = labels[s].get(e.label, 0) + 1
    summary = DatasetSummary(
        name=st["name"], kind=st["kind"], root=root, out_dir=out_dir, splits_file=splits_path,
        splits_reused=reused, images={s: len(split_images[s]) for s in SPLITS}, labels=labels,
    )
    for split, fov in wanted:
        _ensure_episode_file(summary, st, fp, split, fov, split_images[split], force, rewrite, reused, say)
    return summary


def _check_episode_pitch_bound(st: Mapping[str, Any], pitch_bound: int, first_file: Path) -> None:
    """Raise :class:`DatasetError` when the run clamps the pitch at another bound than the static episodes."""
    eb = st["episode_pitch_bound"]
    if check_pitch_bound(pitch_bound) == eb:
        return
    pb = int(pitch_bound)
    cmd = make_dataset_command(st, episode_pitch_bound=pb, out_dir=f"{st['out_dir']}_pitch{pb}")
    raise DatasetError(
        f"{first_file}: the static episodes of dataset {st['name']!r} have pitches "
        f"within +-{eb} degrees (dataset.episode_pitch_bound={eb}) but this run clamps the pitch at "
        f"task.pitch_bound={pb}; make episodes for it with: "
        f"{cmd} "
        f"and pass the same dataset.* overrides to this run (or run with task.pitch_bound={eb})"
    )


def _splits_reusable(st: Mapping[str, Any], root: Path, out_dir: Path, fp: str, force: bool, rewrite: bool) -> bool:
    """Whether ``splits.json`` exists and was made with these settings (``rewrite=False``: a stale or unreadable
    one raises :class:`DatasetError` naming the command that rebuilds it)."""
    splits_path = out_dir / SPLITS_FILE
    if force or not splits_path.is_file():
        return False
    try:
        doc = read_splits(out_dir)
    except (ValueError, OSError) as e:
        if not rewrite:
            raise DatasetError(f"{splits_path} is unreadable ({' '.join(str(e).split())}); rebuild it with: "
                               f"{make_dataset_command(st)}") from None
        return False
    if doc.get("fingerprint") == fp:  # a file's header, not config: older files have no fingerprint
        return True
    if not rewrite:
        raise DatasetError(
            f"{splits_path} was made for other dataset settings ({_splits_mismatch(doc, st, root)}) and is not "
            f"overwritten here: rebuild it and the episode files with: "
            f"{make_dataset_command(st, **_splits_overrides(doc, st, root))} "
            f"plus this run's dataset.* overrides (or choose another dataset.out_dir)"
        )
    return False


def _split_images(st: Mapping[str, Any], root: Path, out_dir: Path, fp: str, reused: bool, progress: bool,
                  say: Callable[[str], None]) -> dict[str, list[ImageEntry]]:
    """The images of every split: read from ``splits.json`` (``reused``) or discovered (synthetic ones made),
    validated, split and written."""
    entries: list[ImageEntry] | None = None
    if st["kind"] == "synthetic":
        say(f"synthetic images under {root}")
        entries = ensure_synthetic_images(root, st["num_images"], st["seed"], st["width"], st["labels"], progress)
    if reused:
        say(f"reusing {out_dir / SPLITS_FILE}")
        return {s: load_split(out_dir, s) for s in SPLITS}
    # a sun360 list such as indoor+outdoor is split folder by folder, so that each folder's images land in the
    # splits they have in that folder's own data set (no test image of dataset.subset=outdoor trains here)
    parts = sun360_parts(st["subset"]) if st["kind"] == "sun360" and entries is None else (st["subset"],)
    split_images = {s: [] for s in SPLITS}
    for part in parts:
        found = entries if entries is not None else discover(st["kind"], root, part)
        say(f"found {len(found)} images under {root}" + (f" ({part})" if len(parts) > 1 else ""))
        if st["validate"]:
            validate_images(found, progress=progress)
        for s, images in split_entries(found, root, st["split"], st["split_seed"]).items():
            split_images[s].extend(images)
    for s in SPLITS:
        split_images[s].sort()
    extra = {"kind": st["kind"], "subset": st["subset"], "fingerprint": fp}
    write_splits(out_dir, split_images, dataset=st["name"], root=root, seed=st["split_seed"], ratios=st["split"], extra=extra)
    say(f"wrote {out_dir / SPLITS_FILE}")
    return split_images


def _ensure_episode_file(summary: DatasetSummary, st: Mapping[str, Any], fp: str, split: str, fov: float,
                         images: list[ImageEntry], force: bool, rewrite: bool, reused: bool,
                         say: Callable[[str], None]) -> None:
    """Reuse, take the first K of, extend, refuse or (re)write the static episode file of ``(split, fov)``;
    records what happened in ``summary``."""
    K, ms, eb = st["episodes_per_image"], st["episode_max_steps"], st["episode_pitch_bound"]
    path = episode_file(summary.out_dir, split, fov)
    efp = _episodes_fingerprint(fp, split, fov, K, st)
    header = None if force or not path.is_file() else _read_episode_header(path)
    key = (split, fov)
    summary.episode_files[key] = path
    if header is not None and header.get("fingerprint") == efp and (reused or not rewrite):
        summary.episode_counts[key] = dict(header.get("difficulty_counts", {}))
        summary.episodes_reused[key] = True
        return
    have = _made_with_k(header, fp, split, fov, st) if not rewrite and header is not None else None
    if have is not None and have > K:  # more episodes per image than asked for: the tool takes the first K
        summary.episode_counts[key] = {d: int(n) * K // have for d, n in header["difficulty_counts"].items()}
        summary.episodes_reused[key] = True
        return
    if have is not None:  # fewer: the file made with K keeps the ones it holds as its first ones (nested)
        say(f"extending {path} from {have} to {K} episodes per image (its episodes stay)")
    elif not rewrite and path.is_file():
        why = "unreadable header" if header is None else _episodes_mismatch(header, st)
        fix = {} if header is None else {
            k: new for k, (old, new) in _episodes_recorded(header, st).items() if old != new
        }
        raise DatasetError(
            f"{path} was made for other settings ({why}) and is not overwritten here: rebuild it with: "
            f"{make_dataset_command(st, **fix)} plus this run's dataset.* overrides (or choose another dataset.out_dir)"
        )
    episodes = make_static_episodes(images, split, fov, K, st["episode_seed"], eb, ms, st["hard_rule"])
    counts = {d: sum(1 for e in episodes if e.difficulty == d) for d in DIFFICULTIES}
    write_episode_file(
        path, episodes, dataset=st["name"], root=summary.root, split=split, fov=fov, hard_rule=st["hard_rule"],
        seed=st["episode_seed"],
        extra={"episodes_per_image": K, "nested": True, "pitch_bound": eb, "max_steps": ms, "fingerprint": efp,
               "difficulty_counts": counts},
    )
    summary.episode_counts[key] = counts
    summary.episodes_reused[key] = False
    say(f"wrote {path}")


def _made_with_k(header: Mapping[str, Any], splits_fp: str, split: str, fov: float, st: Mapping[str, Any]) -> int | None:
    """The ``episodes_per_image`` an episode file was made with, when it matches ``st`` in every other setting
    (``None`` otherwise). The fingerprint includes the nested layout of ``K > 1`` files, so such a file is
    nested: its first ``k`` episodes per image are the file made with ``k``, for any ``k``."""
    have = header.get("episodes_per_image")
    if isinstance(have, bool) or not isinstance(have, int):
        return None
    return have if header.get("fingerprint") == _episodes_fingerprint(splits_fp, split, fov, have, st) else None
