"""A base for the small stand-in networks the agent tests give :class:`~findview_baselines.agents.ppo_agent.PPOAgent`
in place of a trained policy: the attributes the agent reads from a network, and a one-number GRU state."""

from __future__ import annotations

import torch


class StandInPolicy(torch.nn.Module):
    """What the agent reads from a network besides ``forward``: its view size (``height`` x ``width`` pixels), no
    search-memory inputs, light work (one thread), and a (num_envs, 1) zero initial state. Subclasses write
    ``forward(obs, hidden, masks, memory=None) -> (Categorical over the 5 actions, values (B,), new hidden)``."""

    height = width = 8
    memory_inputs = 0
    heavy = False

    def initial_hidden(self, num_envs: int, device: torch.device | str | None = None) -> torch.Tensor:
        return torch.zeros(num_envs, 1, device=device)
