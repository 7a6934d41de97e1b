"""Uniformly random actions (a lower bound for every metric)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import torch

from findview.episode import Episode
from findview.runtime import light_work
from findview_baselines.agents.base import NUM_ACTIONS, Agent

if TYPE_CHECKING:
    from findview_baselines.config import RandomAgentConfig


class RandomAgent(Agent):
    """Draws each action uniformly from the 5 actions with a seeded ``torch.Generator``.

    The stream depends only on ``seed`` and on the sequence of ``act`` calls, so a run is reproducible.
    """

    name = "random"

    def __init__(self, num_envs: int, device: str | torch.device = "cpu", seed: int = 0) -> None:
        super().__init__(num_envs, device, seed)
        self.generator = torch.Generator(device="cpu")
        self.generator.manual_seed(self.seed)

    @classmethod
    def from_config(cls, cfg: "RandomAgentConfig", num_envs: int, device: str | torch.device, seed: int) -> "RandomAgent":
        """Factory for :func:`~findview_baselines.agents.make_agent` (the config has no setting besides the name)."""
        del cfg
        return cls(num_envs, device, seed)

    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        super().reset(env_ids, episodes)

    @light_work()
    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, _ = self._check_obs(obs)
        a = torch.randint(0, NUM_ACTIONS, (self.num_envs,), generator=self.generator, dtype=torch.int64)
        return a.to(view.device)
