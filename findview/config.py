"""Typed config schemas of the core: ``sim``, ``task`` (with ``task.reward``), ``dataset``, ``corruption``.

Each dataclass is the schema of one Hydra config group. :func:`register_core_configs` stores them in
Hydra's ConfigStore as ``base_<group>`` at the root, outside the groups (so that ``--help`` lists only
the files a user picks); every YAML file of the group starts with ``defaults: [/base_<group>@_here_,
_self_]``, so a wrong type or an unknown key fails when the config is
composed (before any work starts). Value ranges that a type cannot express are checked by
``__post_init__``, which runs when the tools turn the composed config into objects
(:func:`findview_baselines.cli.validate_config`); the messages name the full key.

The field docstrings are the documentation of every key (units: degrees, pixels, steps, MiB). The task
itself (conventions, difficulties, metrics, rewards) is described in docs/TASK.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional, TypeVar

from findview.task.rewards import RewardConfig

__all__ = [
    "ConfigError",
    "SimConfig",
    "RewardConfig",
    "TaskConfig",
    "DatasetConfig",
    "CorruptionConfig",
    "register_core_configs",
    "check",
    "as_section",
]

T = TypeVar("T")


class ConfigError(ValueError):
    """A config value a user set is not acceptable; the message names the key, the value and what was
    expected (the tools print it as one line and exit with status 2)."""


def check(ok: bool, key: str, value: Any, expected: str) -> None:
    """Raise :class:`ConfigError` ``"<key>=<value>: expected <expected>"`` unless ``ok``."""
    if not ok:
        raise ConfigError(f"{key}={value!r}: expected {expected}")


SIM_MODES = ("bilinear", "nearest", "bicubic")
SIM_BACKENDS = ("auto", "opencv", "torch")
DATASET_KINDS = ("synthetic", "sun360", "indoor360", "folder")
HARD_RULES = ("or", "and")


@dataclass
class SimConfig:
    """The renderer (``sim`` group; ``sim=fov90`` is the paper's main setting, ``sim=fov60`` its appendix)."""

    fov: float = 90.0
    """Horizontal field of view of the perspective views, degrees, in (0, 180)."""
    height: int = 256
    """View height, pixels."""
    width: int = 256
    """View width, pixels."""
    mode: str = "bilinear"
    """Panorama sampling: bilinear | nearest | bicubic."""
    backend: str = "auto"
    """Renderer: auto (OpenCV remap for uint8 panoramas on the CPU, torch elsewhere) | opencv | torch."""
    device: str = "auto"
    """Where panoramas, views and the environment state live: auto (cuda if available) | cpu | cuda | cuda:N."""
    bank_mb: float = 2048.0
    """Memory bound of the decoded-panorama bank on sim.device, MiB. When it holds every panorama the run
    uses (e.g. the whole train split: SUN360 indoor at 1024x512 is about 18 GB, 1.5 MiB a panorama),
    each is decoded once and stays resident as uint8; otherwise the bank is an LRU cache that streams from
    disk with background prefetch of upcoming episodes' panoramas."""
    equi_height: Optional[int] = None
    """Panorama height He in pixels that every panorama is resized to (width 2 He); null keeps the first
    panorama's size (all panoramas of a data set normally share it)."""
    prefetch_workers: int = 2
    """Background panorama-decoding threads (0 decodes inline)."""

    def __post_init__(self) -> None:
        check(0 < self.fov < 180, "sim.fov", self.fov, "a field of view in (0, 180) degrees")
        check(self.height >= 8, "sim.height", self.height, "a view height of at least 8 pixels")
        check(self.width >= 8, "sim.width", self.width, "a view width of at least 8 pixels")
        check(self.mode in SIM_MODES, "sim.mode", self.mode, " | ".join(SIM_MODES))
        check(self.backend in SIM_BACKENDS, "sim.backend", self.backend, " | ".join(SIM_BACKENDS))
        check(self.bank_mb > 0, "sim.bank_mb", self.bank_mb, "a positive size in MiB")
        check(self.equi_height is None or self.equi_height >= 8, "sim.equi_height", self.equi_height,
              "null or a panorama height of at least 8 pixels")
        check(self.prefetch_workers >= 0, "sim.prefetch_workers", self.prefetch_workers, "0 or more threads")


@dataclass
class TaskConfig:
    """Episode rules (``task`` group; docs/TASK.md, section Episodes)."""

    max_steps: int = 5000
    """T: an episode is force-stopped after this many steps (stop counts as a step)."""
    pitch_bound: int = 60
    """Pitch is clamped to [-pitch_bound, pitch_bound], degrees (<= 90)."""
    step_deg: int = 1
    """Degrees per move."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    """Rewards for reinforcement learning."""

    def __post_init__(self) -> None:
        check(self.max_steps >= 1, "task.max_steps", self.max_steps, "a positive number of steps")
        check(0 <= self.pitch_bound <= 90, "task.pitch_bound", self.pitch_bound, "an integer in [0, 90] degrees")
        check(self.step_deg >= 1, "task.step_deg", self.step_deg, "a positive integer number of degrees")


@dataclass
class DatasetConfig:
    """A data set of equirectangular panoramas, its splits and its static val/test episodes (``dataset``
    group; docs/TASK.md, section Datasets and splits)."""

    name: str = "synthetic"
    """Data set name (used in output folder names)."""
    kind: str = "synthetic"
    """Layout: synthetic | sun360 | indoor360 | folder."""
    root: Optional[str] = None
    """Folder with the panoramas (synthetic: where they are generated)."""
    subset: Optional[str] = None
    """sun360 only: indoor | outdoor | others | all, or several folders joined by '+' (indoor+outdoor: each folder
    split on its own, so its val / test images are those of its own data set)."""
    out_dir: str = "data/${.name}"
    """Where splits.json and episodes/ are written (relative paths: the launch folder)."""
    split: list[float] = field(default_factory=lambda: [0.8, 0.1, 0.1])
    """Train / val / test ratios within each label (sub-category)."""
    split_seed: int = 0
    """Seed of the split order."""
    episodes_per_image: int = 1
    """Static val/test episodes per image and difficulty."""
    episode_seed: int = 0
    """Seed of the static episodes."""
    episode_fovs: list[float] = field(default_factory=lambda: [90.0, 60.0])
    """Fields of view (degrees) with an episode file each; tools use the file of sim.fov."""
    episode_pitch_bound: int = 60
    """Static episodes: init and target pitches within [-b, b] degrees (must equal task.pitch_bound)."""
    episode_max_steps: int = 5000
    """Static episodes: shortest paths satisfy 10 < L1 < this many steps (independent of task.max_steps, so
    the benchmark episodes never depend on which tool ran last)."""
    hard_rule: str = "or"
    """Hard difficulty: or = |dpitch| > f OR dyaw > f (the published numbers); and = the paper's text."""
    splits_to_make: list[str] = field(default_factory=lambda: ["val", "test"])
    """Splits with static episode files (train episodes are sampled on the fly)."""
    validate: bool = True
    """Decode every image when (re)building the splits."""
    num_images: int = 40
    """synthetic only: number of panoramas (image i gets label labels[i % len(labels)])."""
    seed: int = 0
    """synthetic only: generator seed."""
    width: int = 1024
    """synthetic only: panorama width, pixels (height = width / 2)."""
    labels: list[str] = field(default_factory=lambda: ["room", "hall", "landscape", "village"])
    """synthetic only: scene kinds."""

    def __post_init__(self) -> None:
        check(self.kind in DATASET_KINDS, "dataset.kind", self.kind, " | ".join(DATASET_KINDS))
        check(self.hard_rule in HARD_RULES, "dataset.hard_rule", self.hard_rule, "or | and")
        check(len(self.split) == 3 and all(r >= 0 for r in self.split) and sum(self.split) > 0,
              "dataset.split", list(self.split), "three non-negative ratios [train, val, test]")
        check(self.episodes_per_image >= 0, "dataset.episodes_per_image", self.episodes_per_image, "0 or more episodes")
        check(all(0 < f < 180 for f in self.episode_fovs), "dataset.episode_fovs", list(self.episode_fovs),
              "fields of view in (0, 180) degrees")
        bad = [s for s in self.splits_to_make if s not in ("train", "val", "test")]
        check(not bad, "dataset.splits_to_make", list(self.splits_to_make), "a list of train | val | test")
        check(self.num_images >= 1, "dataset.num_images", self.num_images, "a positive integer")
        check(self.width >= 16 and self.width % 2 == 0, "dataset.width", self.width, "an even width of at least 16 pixels")


@dataclass
class CorruptionConfig:
    """Target-image corruptions (``corruption`` group; docs/TASK.md, section Corruptions).

    Applied to the target image only, once per episode, from the episode's seed; the current view stays
    clean.
    """

    name: Any = "none"
    """One corruption name, a list of names, a category (blur | noise | digital | weather), all, or none."""
    severity: Any = 3
    """Severity 1-5, or [low, high] to draw one per episode."""
    ramp_updates: int = 0
    """Training only: raise the highest severity from `low` to `high` linearly over this many updates
    (0: no ramp)."""
    clean_fraction: float = 0.0
    """Share of episodes (0-1, drawn per episode from its seed) whose target stays clean although a
    corruption is named: training with corruptions keeps seeing exact matches. 0 keeps every episode's draw
    as it was."""
    weights: Any = None
    """Relative draw weight per corruption name, e.g. {fog: 3, frost: 2} (names left out weigh 1; each a
    name that `name` draws). None draws uniformly, exactly as before the option existed."""

    def __post_init__(self) -> None:
        sev = self.severity
        levels = list(sev) if isinstance(sev, (list, tuple)) else [sev]
        ok = (
            1 <= len(levels) <= 2
            and all(isinstance(s, int) and not isinstance(s, bool) and 1 <= s <= 5 for s in levels)
            and levels == sorted(levels)
        )
        check(ok, "corruption.severity", sev, "an integer 1-5 or a range [low, high] within 1-5")
        check(self.ramp_updates >= 0, "corruption.ramp_updates", self.ramp_updates, "0 or more updates")
        check(0.0 <= self.clean_fraction < 1.0, "corruption.clean_fraction", self.clean_fraction, "a share in [0, 1)")
        from findview.corruptions import check_frost_textures, resolve_names  # deferred: keeps imports light

        name = list(self.name) if isinstance(self.name, (list, tuple)) else self.name
        try:
            names = resolve_names(name)
        except ValueError as err:
            raise ConfigError(f"corruption.name={name!r}: {err}") from None
        if self.weights is not None:
            weights = self.weights
            check(hasattr(weights, "items") and all(isinstance(k, str) for k in weights), "corruption.weights", weights,
                  "a mapping from corruption names to weights, e.g. {fog: 3, frost: 2}")
            unknown = sorted(set(weights) - set(names))
            check(not unknown, "corruption.weights", dict(weights), f"weights only for the drawn names {list(names)}")
            values = [w for w in weights.values()]
            numeric = all(isinstance(w, (int, float)) and not isinstance(w, bool) and w >= 0 for w in values)
            total = sum(values) + len(set(names) - set(weights)) if numeric else 0
            check(numeric and total > 0, "corruption.weights", dict(weights), "numbers >= 0, not all 0")
        if "frost" in names:
            try:
                check_frost_textures()
            except FileNotFoundError as err:
                raise ConfigError(f"corruption.name={name!r}: {err}") from None


def register_core_configs() -> None:
    """Store the core schemas in Hydra's ConfigStore (``base_<group>``, at the root: not an option of the
    group, hidden from ``--help``; the group's YAML files name it as ``/base_<group>@_here_``). Idempotent."""
    from hydra.core.config_store import ConfigStore

    cs = ConfigStore.instance()
    cs.store(name="base_sim", node=SimConfig)
    cs.store(name="base_task", node=TaskConfig)
    cs.store(name="base_dataset", node=DatasetConfig)
    cs.store(name="base_corruption", node=CorruptionConfig)


def as_section(obj: Any, schema: type[T]) -> T:
    """The boundary conversion for code outside the tools (tests, benchmarks, notebooks): ``obj`` as a validated
    ``schema`` object. An instance of ``schema`` is returned as it is; ``None`` gives the schema's defaults; a
    mapping or a ``DictConfig`` is merged onto the schema (an unknown key or a wrong type raises OmegaConf's
    error naming it), its interpolations resolved and its range checks run (:class:`ConfigError`).

    The builders (:mod:`findview.build`, :mod:`findview.dataset.prepare`) take the objects only."""
    if isinstance(obj, schema):
        return obj
    from omegaconf import OmegaConf

    node = OmegaConf.structured(schema)
    if obj is not None:
        node = OmegaConf.merge(node, obj)
    return OmegaConf.to_object(node)  # type: ignore[return-value]
