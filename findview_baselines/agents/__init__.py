"""Baseline agents behind one batched interface (see :mod:`findview_baselines.agents.base`).

``make_agent(name, cfg, num_envs, device, seed)`` builds one by name from its typed config (the schemas are in
findview_baselines/config.py):

- ``random``: uniform actions (seeded);
- ``oracle``: shortest path from the episode's privileged rotations (eps 0, SPL 1);
- ``orb`` / ``sift``: the paper's rule-based feature-matching agents (docs/TASK.md, section Rule-based agents);
- ``rotation``: relative-rotation estimation from feature matches + straight walk (beyond the paper);
  its geometry is in ``rotation_geometry``, its photometric check in ``photometric``.

More agents (e.g. a learned policy) can be added with :func:`register_agent`.
"""

from __future__ import annotations

import dataclasses
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
    "default_agent_config",
    "agent_names",
]

#: factory(cfg, num_envs, device, seed, **context) -> Agent; ``cfg`` is the agent's typed config (its schema in
#: findview_baselines/config.py), ``context`` what an agent needs beyond it (``ppo``: checkpoint, height, width)
AgentFactory = Callable[..., Agent]


def _rotation(cfg: Any, num_envs: int, device: "str | torch.device", seed: int) -> Agent:
    """``RotationAgent.from_config`` (agents/rotation.py) reads a mapping of its keys: the typed section as one."""
    return RotationAgent.from_config(dataclasses.asdict(cfg), num_envs, device, seed)


AGENTS: dict[str, AgentFactory] = {
    "random": RandomAgent.from_config,
    "oracle": OracleAgent.from_config,
    "orb": FeatureMatchingAgent.from_config,
    "sift": FeatureMatchingAgent.from_config,
    "rotation": _rotation,
}


def default_agent_config(name: str) -> Any:
    """The typed config of the built-in agent ``name`` with the schema's defaults (what ``make_agent(name)``
    uses without a config; ``dataclasses.replace(default_agent_config("orb"), d_thresh=50)`` for others).

    Raises:
        ValueError: ``name`` is not a built-in agent.
    """
    from findview_baselines import config as c  # deferred: the schemas import the policy, which imports agents

    schemas: dict[str, Callable[[], Any]] = {
        "random": c.RandomAgentConfig,
        "oracle": c.OracleAgentConfig,
        "orb": lambda: c.FeatureAgentConfig(name="orb"),
        "sift": lambda: c.FeatureAgentConfig(name="sift"),
        "rotation": c.RotationAgentConfig,
        "ppo": c.PPOAgentConfig,
    }
    if name not in schemas:
        raise ValueError(f"agent {name!r} has no built-in config; valid: {', '.join(sorted(schemas))}")
    return schemas[name]()


def register_agent(name: str, factory: AgentFactory, overwrite: bool = False) -> None:
    """Make ``make_agent(name, ...)`` call ``factory(cfg, num_envs, device, seed, **context)``."""
    if name in AGENTS and not overwrite:
        raise ValueError(f"agent {name!r} is already registered")
    AGENTS[name] = factory


def agent_names() -> list[str]:
    """The registered agent names, sorted."""
    return sorted(AGENTS)


def make_agent(
    name: str, cfg: Any = None, num_envs: int = 1, device: str | torch.device = "cpu", seed: int = 0, **context: Any
) -> Agent:
    """Build the agent ``name`` for ``num_envs`` slots.

    Args:
        name: a registered name (:func:`agent_names`).
        cfg: the agent's typed config (the validated ``agent`` section: ``FeatureAgentConfig``,
            ``OracleAgentConfig``, ... of findview_baselines/config.py), whose ``name`` must be ``name``;
            ``None``: the schema's defaults.
        num_envs: number of environment slots.
        device: device for the actions when it cannot be taken from the observations.
        seed: seed of the agent's randomness.
        context: what the agent needs beyond its config (``ppo``: ``checkpoint``, ``height``, ``width``).

    Raises:
        ValueError: an unknown name (listing the valid ones), or a config of another agent.
    """
    try:
        factory = AGENTS[name]
    except KeyError:
        raise ValueError(f"unknown agent {name!r}; valid agents: {', '.join(agent_names())}") from None
    if cfg is None:
        cfg = default_agent_config(name)
    if cfg.name != name:
        raise ValueError(f"agent {name!r}: the config given is for agent {cfg.name!r}")
    return factory(cfg, int(num_envs), device, int(seed), **context)
