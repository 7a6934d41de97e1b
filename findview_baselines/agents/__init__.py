"""Baseline agents behind one batched interface (see :mod:`findview_baselines.agents.base`).

``make_agent(name, cfg, num_envs, device, seed)`` builds one by name:

- ``random``: uniform actions (seeded);
- ``oracle``: shortest path from the episode's privileged rotations (eps 0, SPL 1);
- ``orb`` / ``sift``: the paper's rule-based feature-matching agents (docs/TASK.md, section Rule-based agents);
- ``rotation``: relative-rotation estimation from feature matches + straight walk (beyond the paper);
  its geometry is in ``rotation_geometry``, its photometric check in ``photometric``.

More agents (e.g. a learned policy) can be added with :func:`register_agent`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from findview_baselines.agents.base import ACTION_NAMES, NUM_ACTIONS, Action, Agent
from findview_baselines.agents.feature_matching import FeatureMatchingAgent
from findview_baselines.agents.oracle import OracleAgent
from findview_baselines.agents.random_agent import RandomAgent
from findview_baselines.agents.rotation import RotationAgent

__all__ = [
    "Action",
    "ACTION_NAMES",
    "NUM_ACTIONS",
    "Agent",
    "RandomAgent",
    "OracleAgent",
    "FeatureMatchingAgent",
    "RotationAgent",
    "AGENTS",
    "register_agent",
    "make_agent",
    "agent_names",
]

#: factory(cfg, num_envs, device, seed) -> Agent
AgentFactory = Callable[[Any, int, "str | torch.device", int], Agent]

AGENTS: dict[str, AgentFactory] = {
    "random": RandomAgent.from_config,
    "oracle": OracleAgent.from_config,
    "orb": lambda cfg, n, dev, seed: FeatureMatchingAgent.from_config(cfg, n, dev, seed, detector="orb"),
    "sift": lambda cfg, n, dev, seed: FeatureMatchingAgent.from_config(cfg, n, dev, seed, detector="sift"),
    "rotation": RotationAgent.from_config,
}


def register_agent(name: str, factory: AgentFactory, overwrite: bool = False) -> None:
    """Make ``make_agent(name, ...)`` call ``factory(cfg, num_envs, device, seed)``."""
    if name in AGENTS and not overwrite:
        raise ValueError(f"agent {name!r} is already registered")
    AGENTS[name] = factory


def agent_names() -> list[str]:
    """The registered agent names, sorted."""
    return sorted(AGENTS)


def make_agent(
    name: str, cfg: Any = None, num_envs: int = 1, device: str | torch.device = "cpu", seed: int = 0
) -> Agent:
    """Build the agent ``name`` for ``num_envs`` slots.

    Args:
        name: a registered name (:func:`agent_names`).
        cfg: the agent's config (the ``agent`` Hydra group node, a dict, or ``None`` for defaults); its
            ``name`` key is ignored; unknown keys raise ``ValueError`` naming the valid ones.
        num_envs: number of environment slots.
        device: device for the actions when it cannot be taken from the observations.
        seed: seed of the agent's randomness.
    """
    try:
        factory = AGENTS[name]
    except KeyError:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(agent_names())}") from None
    return factory(cfg, int(num_envs), device, int(seed))
