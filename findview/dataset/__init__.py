"""Data sets for FindView: discovery and validation of panoramas, deterministic splits, difficulty rules
and episode sampling, static val/test episode files, and the built-in synthetic panoramas.

Files (schemas in docs/ARCHITECTURE.md): ``<out_dir>/splits.json`` and
``<out_dir>/episodes/<split>_fov<F:g>.json``, written by ``tools/make_dataset.py`` or on demand by
:func:`ensure_dataset`.
"""

from findview.dataset.difficulty import (
    DIFFICULTIES,
    HARD_RULES,
    check_difficulty,
    check_fov,
    check_hard_rule,
    check_pitch_bound,
    difficulty_mask,
    pitch_distribution,
    satisfies,
)
from findview.dataset.discovery import (
    KINDS,
    SUN360_LAYOUT,
    SUN360_SUBSETS,
    sun360_parts,
    DatasetError,
    ImageEntry,
    discover,
    discover_folder,
    discover_indoor360,
    discover_sun360,
    validate_images,
)
from findview.dataset.episodes import episode_file, load_episodes, make_static_episodes, read_episode_file, write_episode_file
from findview.dataset.prepare import DatasetSummary, dataset_settings, ensure_dataset, prepare_dataset
from findview.dataset.sampler import LEVEL_MODES, EpisodeSampler, SamplingError, derive_seed, sample_pitch, sample_rotations
from findview.dataset.splits import SPLITS, SPLITS_FILE, load_split, read_splits, split_entries, write_splits
from findview.dataset.synthetic import SCENE_KINDS, ensure_synthetic_images, generate_panorama

__all__ = [
    "DIFFICULTIES",
    "HARD_RULES",
    "KINDS",
    "LEVEL_MODES",
    "SCENE_KINDS",
    "SPLITS",
    "SPLITS_FILE",
    "SUN360_LAYOUT",
    "SUN360_SUBSETS",
    "sun360_parts",
    "DatasetError",
    "DatasetSummary",
    "EpisodeSampler",
    "ImageEntry",
    "SamplingError",
    "check_difficulty",
    "check_fov",
    "check_hard_rule",
    "check_pitch_bound",
    "dataset_settings",
    "derive_seed",
    "difficulty_mask",
    "discover",
    "discover_folder",
    "discover_indoor360",
    "discover_sun360",
    "ensure_dataset",
    "ensure_synthetic_images",
    "episode_file",
    "generate_panorama",
    "load_episodes",
    "load_split",
    "make_static_episodes",
    "pitch_distribution",
    "prepare_dataset",
    "read_episode_file",
    "read_splits",
    "sample_pitch",
    "sample_rotations",
    "satisfies",
    "split_entries",
    "validate_images",
    "write_episode_file",
    "write_splits",
]
