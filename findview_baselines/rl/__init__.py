"""Learned agents: the recurrent actor-critic policy (``policy``; its image encoders ``encoders``, the
auxiliary rotation head ``aux_head``, the checkpoint signature check ``signature``), rollout storage + GAE
(``storage``), the PPO update (``ppo``), the base of every trainer and the interface the run loop drives
(``trainer_base``: :class:`Trainer`), the PPO update loop (``ppo_trainer``), imitation of the oracle
(``dagger``: the trainer; ``dagger_config``, ``dagger_loss``, ``sequence_buffer``), the learned agents'
search memory (``search_memory``), the difficulty curriculum (``scheduler``), checkpoints (``checkpoint``: the
payload, reading it, ``load_policy``) and run safety (``safety``: folder lock, signals). This is the bottom layer
of the baselines: it imports nothing above it; the training run that drives a trainer is
:mod:`findview_baselines.training`."""

from findview.task import NUM_ACTIONS
from findview_baselines.rl.dagger import DAggerConfig, DAggerTrainer
from findview_baselines.rl.encoders import ConvEncoder
from findview_baselines.rl.policy import VARIANTS, Policy, build_policy
from findview_baselines.rl.ppo import PPO, PPOConfig, linear_decay, ppo_loss
from findview_baselines.rl.ppo_trainer import PPOTrainer
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.signature import check_signature
from findview_baselines.rl.storage import MiniBatch, RolloutStorage
from findview_baselines.rl.trainer_base import Trainer, UpdateAbandoned

__all__ = [
    "NUM_ACTIONS",
    "VARIANTS",
    "ConvEncoder",
    "Policy",
    "build_policy",
    "check_signature",
    "PPO",
    "PPOConfig",
    "linear_decay",
    "ppo_loss",
    "DifficultyScheduler",
    "MiniBatch",
    "RolloutStorage",
    "PPOTrainer",
    "DAggerConfig",
    "DAggerTrainer",
    "Trainer",
    "UpdateAbandoned",
]
