"""The FindView task: actions, rewards, episode sources, the batched environment, a Gymnasium wrapper."""

from findview.task.actions import ACTION_NAMES, NUM_ACTIONS, Action
from findview.task.env import FindViewEnv
from findview.task.rewards import REWARD_NAMES, RewardConfig, compute_reward
from findview.task.sources import SampledEpisodeSource, StaticEpisodeSource

__all__ = [
    "Action", "ACTION_NAMES", "NUM_ACTIONS", "FindViewEnv", "RewardConfig", "REWARD_NAMES", "compute_reward",
    "StaticEpisodeSource", "SampledEpisodeSource",
]
