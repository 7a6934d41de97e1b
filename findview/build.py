"""The one place that builds simulators, environments and episode sources from config sections.

Used by ``tools/train.py`` (training and validation environments), ``tools/eval.py``,
``tools/render_episode.py``, the benchmarks and the tests, so that they all render, clamp, reward and
corrupt the same way. The sections are the validated objects of :mod:`findview.config` (``SimConfig``,
``TaskConfig``, ``CorruptionConfig``); code holding a mapping or a ``DictConfig`` converts it once with
:func:`findview.config.as_section`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from findview.config import CorruptionConfig, SimConfig, TaskConfig
from findview.episode import Episode

__all__ = ["build_simulator", "build_env", "build_static_env", "build_sampled_env", "build_target_transform"]


def build_simulator(sim_cfg: SimConfig, pitch_bound: int, images: Iterable[str], min_slots: int):
    """A :class:`~findview.sim.Simulator` over a :class:`~findview.sim.PanoramaBank` sized for ``images``.

    Args:
        sim_cfg: the ``sim`` section (fov degrees, height / width pixels, mode, backend, device, bank_mb
            MiB, equi_height pixels, prefetch_workers).
        pitch_bound: the task's pitch clamp, degrees.
        images: every panorama path the environments may load (bounds the bank's slot count).
        min_slots: bank slots needed at once (one per environment slot that may be pinned).
    """
    from findview.sim import PanoramaBank, Simulator, resolve_device

    bank = PanoramaBank(
        resolve_device(str(sim_cfg.device)),
        budget_mb=float(sim_cfg.bank_mb),
        equi_height=sim_cfg.equi_height,
        prefetch_workers=int(sim_cfg.prefetch_workers),
        max_panoramas=max(1, len(set(images))),
        min_slots=int(min_slots),
    )
    return Simulator(
        bank,
        fov=float(sim_cfg.fov),
        height=int(sim_cfg.height),
        width=int(sim_cfg.width),
        pitch_bound=int(pitch_bound),
        mode=str(sim_cfg.mode),
        backend=str(sim_cfg.backend),
    )


def build_target_transform(corruption_cfg: CorruptionConfig | None):
    """The per-episode target corruption of the ``corruption`` section, or ``None`` for ``name: none`` (or no
    section)."""
    if corruption_cfg is None:
        return None
    from findview.corruptions import resolve_names

    names = resolve_names(corruption_cfg.name)
    if not names:
        return None
    from findview.task.target_corruption import EpisodeCorruption

    severity = corruption_cfg.severity
    levels = [int(s) for s in severity] if isinstance(severity, Sequence) and not isinstance(severity, str) else [int(severity)]
    weights = {str(k): float(v) for k, v in corruption_cfg.weights.items()} if corruption_cfg.weights else None
    return EpisodeCorruption(names, min(levels), max(levels), float(corruption_cfg.clean_fraction), weights)


def build_env(
    simulator: Any,
    source: Any,
    num_envs: int,
    task_cfg: TaskConfig,
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

    return FindViewEnv(
        simulator,
        source,
        int(num_envs),
        max_steps=int(max_steps if max_steps is not None else task_cfg.max_steps),
        pitch_bound=int(task_cfg.pitch_bound),
        step_deg=int(task_cfg.step_deg),
        reward=task_cfg.reward,
        auto_reset=auto_reset,
        target_transform=target_transform,
    )


def build_static_env(
    sim_cfg: SimConfig,
    task_cfg: TaskConfig,
    episodes: Sequence[Episode],
    num_envs: int,
    *,
    corruption_cfg: CorruptionConfig | None = None,
    max_steps: int | None = None,
    simulator: Any = None,
):
    """Simulator (unless given) + auto-resetting environment playing the fixed ``episodes`` in order
    (validation and evaluation)."""
    from findview.task import StaticEpisodeSource

    pitch_bound = int(task_cfg.pitch_bound)
    if simulator is None:
        simulator = build_simulator(sim_cfg, pitch_bound, [e.image for e in episodes], num_envs)
    return build_env(
        simulator, StaticEpisodeSource(episodes), num_envs, task_cfg,
        max_steps=max_steps, target_transform=build_target_transform(corruption_cfg),
    )


def build_sampled_env(
    sim_cfg: SimConfig,
    task_cfg: TaskConfig,
    sampler: Any,
    num_envs: int,
    *,
    mode: str = "unbounded",
    corruption_cfg: CorruptionConfig | None = None,
    simulator: Any = None,
    extra_images: Iterable[str] = (),
    extra_slots: int = 0,
):
    """Simulator (unless given) + auto-resetting environment with endless episodes from ``sampler``
    (training). ``mode``: the curriculum mode of the source (``unbounded`` | ``bounded``).
    ``extra_images`` / ``extra_slots``: what other environments sharing the simulator need (validation)."""
    from findview.task.sources import SampledEpisodeSource

    pitch_bound = int(task_cfg.pitch_bound)
    if simulator is None:
        images = [im.path if hasattr(im, "path") else str(im) for im in getattr(sampler, "images", [])]
        simulator = build_simulator(sim_cfg, pitch_bound, [*images, *extra_images], num_envs + extra_slots)
    source = SampledEpisodeSource(sampler, level=1, mode=mode)
    return build_env(simulator, source, num_envs, task_cfg, target_transform=build_target_transform(corruption_cfg))
