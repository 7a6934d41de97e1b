"""PPO baseline: recurrent actor-critic policy, rollout storage + GAE, PPO update, difficulty scheduler,
trainer sketch (rollouts, update, evaluation, checkpoints)."""

from findview_baselines.rl.policy import (
    NUM_ACTIONS,
    VARIANTS,
    ConvEncoder,
    Policy,
    build_policy,
    check_signature,
)
from findview_baselines.rl.ppo import PPO, PPOConfig, linear_decay, ppo_loss
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import MiniBatch, RolloutStorage
from findview_baselines.rl.trainer import PPOTrainer, evaluate, load_policy, save_checkpoint

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
    "evaluate",
    "load_policy",
    "save_checkpoint",
]
