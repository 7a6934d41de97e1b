"""Rewards of docs/TASK.md, section Rewards (``paper``) and two variants, batched.

``paper``: ``r_t = r_success + r_dist + r_slack`` with ``r_success = alpha / (eps + beta)`` on stop,
``-alpha`` on a forced stop at T, else 0; ``r_dist = dist_coef * (eps_{t-1} - eps_t)``;
``r_slack = slack``.

``bell``: as ``paper`` but the stop reward is a bell curve, ``(alpha / beta) * exp(-eps^2 / (2 sigma^2))``
(same peak ``alpha / beta`` at eps 0, steeper fall-off: stopping one or two degrees off pays little).

``basic``: no warmer-colder shaping: ``r_success + r_slack`` only (sparse; for ablations).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

REWARD_NAMES = ("paper", "bell", "basic")


@dataclass
class RewardConfig:
    """Reward settings (the ``task.reward`` config section; docs/TASK.md, section Rewards)."""

    name: str = "paper"
    """paper | bell | basic."""
    alpha: float = 100.0
    """Success scale: alpha / (eps + beta) on stop, -alpha on a forced stop at T."""
    beta: float = 10.0
    """Success offset, degrees (> 0)."""
    dist_coef: float = 0.1
    """Warmer-colder shaping per step: dist_coef * (eps_{t-1} - eps_t), eps in degrees."""
    slack: float = -0.01
    """Reward added at every step."""
    bell_sigma: float = 5.0
    """``bell`` only: width of the stop reward's bell curve, degrees (> 0)."""

    def __post_init__(self) -> None:
        if self.name not in REWARD_NAMES:
            raise ValueError(f"task.reward.name={self.name!r}: expected {' | '.join(REWARD_NAMES)}")
        if self.beta <= 0:
            raise ValueError(f"task.reward.beta={self.beta!r}: expected a positive number of degrees")
        if self.bell_sigma <= 0:
            raise ValueError(f"task.reward.bell_sigma={self.bell_sigma!r}: expected a positive number of degrees")


def compute_reward(
    cfg: RewardConfig,
    prev_eps: torch.Tensor,
    eps: torch.Tensor,
    called_stop: torch.Tensor,
    forced_stop: torch.Tensor,
) -> torch.Tensor:
    """Per-env reward ``(N,)`` float32.

    Args:
        prev_eps, eps: ``(N,)`` L1 distance to the target (degrees) before and after the step.
        called_stop: ``(N,)`` bool, the agent chose STOP this step.
        forced_stop: ``(N,)`` bool, the step limit ended the episode without STOP.
    """
    eps_f = eps.to(torch.float32)
    if cfg.name == "bell":
        success = (cfg.alpha / cfg.beta) * torch.exp(-(eps_f**2) / (2 * cfg.bell_sigma**2))
    else:
        success = cfg.alpha / (eps_f + cfg.beta)
    r = torch.where(called_stop, success, torch.zeros_like(eps_f))
    r = torch.where(forced_stop, torch.full_like(r, -cfg.alpha), r)
    if cfg.name != "basic":
        r = r + cfg.dist_coef * (prev_eps - eps).to(torch.float32)
    return r + cfg.slack
