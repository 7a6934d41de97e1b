"""Building a training run from its typed config: the data, the environments, the policy and the trainer
(:func:`build_run`), with the seeding and the val episode choice it needs. Every builder takes the typed
sections of :class:`findview_baselines.config.TrainConfig`."""

from __future__ import annotations

import logging
import random
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np
import torch

from findview.build import build_sampled_env, build_static_env
from findview.config import SimConfig
from findview.episode import Episode
from findview_baselines.config import PPOAgentConfig, TrainConfig
from findview_baselines.errors import UserError
from findview_baselines.rl import distributed
from findview_baselines.rl.policy import Policy, build_policy
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.search_memory import NearVisits, RowSearch
from findview_baselines.rl.trainer_base import Trainer

log = logging.getLogger(__name__)

__all__ = ["RunParts", "build_run", "make_trainer", "load_data", "select_val_episodes", "seed_everything", "rank_sim"]


def seed_everything(seed: int) -> None:
    """Seed torch (CPU + CUDA), numpy's global RNG and Python's ``random``."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def select_val_episodes(episodes: Sequence[Episode], cap: int | None) -> list[Episode]:
    """At most ``cap`` episodes, spread evenly over the difficulties present and, within one, over the list.

    ``cap=None`` (or a cap above the count) keeps all. Order: difficulty groups in first-seen order.
    """
    episodes = list(episodes)
    if cap is None or int(cap) >= len(episodes):
        return episodes
    cap = int(cap)
    if cap <= 0:
        raise UserError(f"trainer.val_episodes must be positive or null, got {cap}")
    groups: dict[str, list[Episode]] = {}
    for ep in episodes:
        groups.setdefault(ep.difficulty, []).append(ep)
    names = list(groups)
    out: list[Episode] = []
    for k, name in enumerate(names):
        group = groups[name]
        n = min(len(group), cap // len(names) + (1 if k < cap % len(names) else 0))
        out += [group[i * len(group) // n] for i in range(n)]
    return out


def load_data(cfg: TrainConfig, progress: bool) -> tuple[list[Any], list[Episode]]:
    """(train images, val episodes) of the configured dataset; makes the dataset files if missing."""
    from findview.dataset import ensure_dataset, episode_file, load_episodes, load_split

    fov = float(cfg.sim.fov)
    out_dir = ensure_dataset(cfg.dataset, [fov], pitch_bound=cfg.task.pitch_bound, progress=progress, log=log.info)
    train_images = load_split(out_dir, "train")
    if not train_images:
        raise UserError(f"the train split of dataset {cfg.dataset.name!r} in {out_dir} is empty")
    path = episode_file(out_dir, "val", fov)
    # a file made with more episodes per image serves its first k per image (nested files)
    val_episodes = load_episodes(path, episodes_per_image=cfg.dataset.episodes_per_image) if path.is_file() else []
    return train_images, val_episodes


def rank_sim(sim: SimConfig) -> SimConfig:
    """The ``sim`` section of this process: under torchrun on CUDA, one GPU per rank (``cuda:<local rank>``)."""
    if not distributed.is_active():
        return sim
    from findview.sim import resolve_device

    if resolve_device(sim.device).type == "cuda":
        return replace(sim, device=f"cuda:{distributed.local_rank()}")
    return sim


def make_trainer(cfg: TrainConfig, env: Any, policy: Policy, scheduler: DifficultyScheduler, seed: int) -> Trainer:
    """The trainer of ``trainer.algorithm`` (``ppo`` | ``dagger``) around ``env`` and ``policy``; ``seed`` seeds its
    own generators (rank ``r`` passes its own)."""
    t, agent = cfg.trainer, cfg.agent
    set_level = lambda k: setattr(env.source, "level", k)  # noqa: E731
    if t.algorithm == "dagger":
        from findview_baselines.rl.dagger import DAggerTrainer

        return DAggerTrainer(env, policy, t.dagger, t.num_updates, scheduler, set_level, seed=seed,
                             revisit_penalty=agent.revisit_penalty, revisit_rows=RowSearch.of(agent),
                             revisit_near=NearVisits.of(agent))
    from findview_baselines.rl.ppo_trainer import PPOTrainer

    if agent.memory_inputs:
        raise UserError("agent.memory_inputs=true is trained with trainer=dagger only (PPO's rollout storage does not "
                        "keep the search memory's features)")
    return PPOTrainer(env, policy, t.ppo, t.num_updates, scheduler, set_level, seed=seed)


@dataclass
class RunParts:
    """What :func:`build_run` made: the trainer (with its environment and policy) and, on rank 0 when the run
    validates, the val environment and episodes."""

    trainer: Trainer
    val_env: Any
    val_episodes: list[Episode]


def _val_env_count(cfg: TrainConfig, val_episodes: Sequence[Episode]) -> int:
    return min(cfg.trainer.val_num_envs or cfg.trainer.num_envs, len(val_episodes)) if val_episodes else 0


def build_run(cfg: TrainConfig, seed: int, progress: bool) -> RunParts:
    """Data (made if missing; rank 0 first), this rank's shard of the train images, the sampled training
    environments, the val environment (rank 0), the policy and the trainer. ``seed``: this rank's seed."""
    t, sim = cfg.trainer, rank_sim(cfg.sim)
    if sim.height % cfg.agent.downsample or sim.width % cfg.agent.downsample:
        raise UserError(f"agent.downsample={cfg.agent.downsample} must divide the rendered view size "
                        f"sim.height x sim.width = {sim.height}x{sim.width}")
    main = distributed.is_main()
    train_images, val_all = distributed.main_first(lambda: load_data(cfg, progress))
    train_images = distributed.shard(train_images, distributed.rank(), distributed.world_size())
    need_val = t.val_at_end or t.val_interval > 0
    val_episodes = select_val_episodes(val_all, t.val_episodes) if need_val and main else []
    if need_val and main and not val_episodes:
        log.warning("no val episodes: validation and best.pth are skipped")

    from findview.dataset import EpisodeSampler

    s = cfg.scheduler
    scheduler = DifficultyScheduler(t.num_updates, num_levels=s.num_levels, mode=s.mode, start_level=s.start_level)
    sampler = EpisodeSampler(train_images, float(sim.fov), seed=seed, pitch_bound=cfg.task.pitch_bound,
                             max_steps=cfg.task.max_steps, hard_rule=cfg.dataset.hard_rule)
    val_envs = _val_env_count(cfg, val_episodes)
    env = build_sampled_env(sim, cfg.task, sampler, t.num_envs, mode=scheduler.mode, corruption_cfg=cfg.corruption,
                            extra_images=[e.image for e in val_episodes], extra_slots=val_envs)
    val_env = None
    if val_episodes:
        val_env = build_static_env(sim, cfg.task, val_episodes, val_envs, corruption_cfg=cfg.corruption,
                                   max_steps=t.val_max_steps, simulator=env.sim)
    k = cfg.agent.downsample
    if k > 1:  # the network takes the rendered views averaged down (rl/observations.py)
        from findview_baselines.rl.observations import DownsampledEnv

        env = DownsampledEnv(env, k)
    policy = build_policy(cfg.agent, sim.height // k, sim.width // k).to(env.device)
    return RunParts(make_trainer(cfg, env, policy, scheduler, seed), val_env, val_episodes)


def make_val_agent(agent: PPOAgentConfig, policy: Policy, num_envs: int, seed: int) -> Any:
    """The learned-agent wrapper validation plays with (the same as ``tools/eval.py checkpoint=...``)."""
    from findview_baselines.agents.ppo_agent import PPOAgent

    return PPOAgent(policy, num_envs, next(policy.parameters()).device, seed, sample=agent.sample,
                    revisit_penalty=agent.revisit_penalty, revisit_rows=RowSearch.of(agent), fov=agent.fov,
                    revisit_near=NearVisits.of(agent))
