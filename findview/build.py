"""The one place that builds simulators, environments and episode sources from config sections.

Used by ``tools/train.py`` (training and validation environments), ``tools/eval.py``,
``tools/render_episode.py``, the benchmarks and the tests, so that they all render, clamp, reward and
corrupt the same way. Config sections may be Hydra ``DictConfig`` nodes, the dataclasses of
:mod:`findview.config`, or plain mappings.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any


from findview.episode import Episode

__all__ = ["section_get", "build_simulator", "build_env", "build_static_env", "build_sampled_env", "build_target_transform"]


def section_get(section: Any, key: str, default: Any = None) -> Any:
    """``section.key`` for a DictConfig / dataclass / mapping; ``default`` when missing or null."""
    if section is None:
        return default
    if isinstance(section, Mapping):
        value = section.get(key, default)
    else:
        try:
            value = section.get(key, default) if hasattr(section, "get") else getattr(section, key, default)
        except Exception:
            value = getattr(section, key, default)
    return default if value is None else value


def build_simulator(sim_cfg: Any, pitch_bound: int, images: Iterable[str], min_slots: int):
    """A :class:`~findview.sim.Simulator` over a :class:`~findview.sim.PanoramaBank` sized for ``images``.

    Args:
        sim_cfg: the ``sim`` section (fov degrees, height / width pixels, mode, backend, device, bank_mb
            MiB, equi_height pixels, prefetch_workers).
        pitch_bound: the task's pitch clamp, degrees.
        images: every panorama path the environments may load (bounds the bank's slot count).
        min_slots: bank slots needed at once (one per environment slot that may be pinned).
    """
    from findview.sim import PanoramaBank, Simulator, resolve_device

    device = resolve_device(str(section_get(sim_cfg, "device", "auto")))
    bank = PanoramaBank(
        device,
        budget_mb=float(section_get(sim_cfg, "bank_mb", 2048)),
        equi_height=section_get(sim_cfg, "equi_height"),
        prefetch_workers=int(section_get(sim_cfg, "prefetch_workers", 2)),
        max_panoramas=max(1, len(set(images))),
        min_slots=int(min_slots),
    )
    return Simulator(
        bank,
        fov=float(section_get(sim_cfg, "fov", 90)),
        height=int(section_get(sim_cfg, "height", 256)),
        width=int(section_get(sim_cfg, "width", 256)),
        pitch_bound=int(pitch_bound),
        mode=str(section_get(sim_cfg, "mode", "bilinear")),
        backend=str(section_get(sim_cfg, "backend", "auto")),
    )


def build_target_transform(corruption_cfg: Any):
    """The per-episode target corruption of the ``corruption`` section, or ``None`` for ``name: none``."""
    if corruption_cfg is None:
        return None
    from findview.corruptions import resolve_names

    names = resolve_names(section_get(corruption_cfg, "name", "none"))
    if not names:
        return None
    from findview.task.target_corruption import EpisodeCorruption

    severity = section_get(corruption_cfg, "severity", 3)
    levels = [int(s) for s in severity] if isinstance(severity, Sequence) and not isinstance(severity, str) else [int(severity)]
    return EpisodeCorruption(names, min(levels), max(levels), float(section_get(corruption_cfg, "clean_fraction", 0.0)))


def build_env(
    simulator: Any,
    source: Any,
    num_envs: int,
    task_cfg: Any,
    *,
    max_steps: int | None = None,
    target_transform: Any = None,
    auto_reset: bool = True,
):
    """A :class:`~findview.task.FindViewEnv` with the ``task`` section's rules and rewards.

    Args:
        max_steps: overrides ``task.max_steps`` (e.g. a shorter T for validation during training).
        target_transform: applied once to every new target (see :func:`build_target_transform`).
    """
    from findview.task import FindViewEnv
    from findview.task.rewards import RewardConfig

    reward = section_get(task_cfg, "reward")
    if reward is not None and not isinstance(reward, RewardConfig):
        keys = ("name", "alpha", "beta", "dist_coef", "slack", "bell_sigma")
        reward = RewardConfig(**{k: section_get(reward, k) for k in keys if section_get(reward, k) is not None})
    return FindViewEnv(
        simulator,
        source,
        int(num_envs),
        max_steps=int(max_steps if max_steps is not None else section_get(task_cfg, "max_steps", 5000)),
        pitch_bound=int(section_get(task_cfg, "pitch_bound", 60)),
        step_deg=int(section_get(task_cfg, "step_deg", 1)),
        reward=reward,
        auto_reset=auto_reset,
        target_transform=target_transform,
    )


def build_static_env(
    sim_cfg: Any,
    task_cfg: Any,
    episodes: Sequence[Episode],
    num_envs: int,
    *,
    corruption_cfg: Any = None,
    max_steps: int | None = None,
    simulator: Any = None,
):
    """Simulator (unless given) + auto-resetting environment playing the fixed ``episodes`` in order
    (validation and evaluation)."""
    from findview.task import StaticEpisodeSource

    pitch_bound = int(section_get(task_cfg, "pitch_bound", 60))
    if simulator is None:
        simulator = build_simulator(sim_cfg, pitch_bound, [e.image for e in episodes], num_envs)
    return build_env(
        simulator, StaticEpisodeSource(episodes), num_envs, task_cfg,
        max_steps=max_steps, target_transform=build_target_transform(corruption_cfg),
    )


def build_sampled_env(
    sim_cfg: Any,
    task_cfg: Any,
    sampler: Any,
    num_envs: int,
    *,
    mode: str = "unbounded",
    corruption_cfg: Any = None,
    simulator: Any = None,
    extra_images: Iterable[str] = (),
    extra_slots: int = 0,
):
    """Simulator (unless given) + auto-resetting environment with endless episodes from ``sampler``
    (training). ``mode``: the curriculum mode of the source (``unbounded`` | ``bounded``).
    ``extra_images`` / ``extra_slots``: what other environments sharing the simulator need (validation)."""
    from findview.task.sources import SampledEpisodeSource

    pitch_bound = int(section_get(task_cfg, "pitch_bound", 60))
    if simulator is None:
        images = [im.path if hasattr(im, "path") else str(im) for im in getattr(sampler, "images", [])]
        simulator = build_simulator(sim_cfg, pitch_bound, [*images, *extra_images], num_envs + extra_slots)
    source = SampledEpisodeSource(sampler, level=1, mode=mode)
    return build_env(simulator, source, num_envs, task_cfg, target_transform=build_target_transform(corruption_cfg))
