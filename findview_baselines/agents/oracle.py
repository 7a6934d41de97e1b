"""The oracle: walks a shortest path to the target using the episode's privileged rotations."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from findview.episode import Episode
from findview.geometry import wrap_yaw
from findview.runtime import light_work
from findview_baselines.agents.base import DOWN, LEFT, RIGHT, STOP, UP, Agent

if TYPE_CHECKING:
    from findview_baselines.config import OracleAgentConfig

ORDERS = ("pitch_first", "yaw_first")


class OracleAgent(Agent):
    """Dead-reckons its rotation from the episode's start and walks the shortest path, then STOPs.

    The rotation is tracked with the environment's rules (pitch clamped to ``[-pitch_bound,
    pitch_bound]``, yaw wrapped into ``(-180, 180]``, ``step_deg`` degrees a move), so on any valid
    episode the oracle ends with ``eps = 0`` after ``L* = |dpitch0| + dyaw0 + 1`` steps (SPL 1).

    Args:
        order: ``"pitch_first"`` or ``"yaw_first"`` (both are shortest paths).
        pitch_bound: pitch clamp in degrees (the task's ``pitch_bound``).
        step_deg: degrees per move (the task's ``step_deg``).
    """

    name = "oracle"

    def __init__(
        self,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        order: str = "pitch_first",
        pitch_bound: int = 60,
        step_deg: int = 1,
    ) -> None:
        super().__init__(num_envs, device, seed)
        if order not in ORDERS:
            raise ValueError(f"oracle: order must be one of {ORDERS}, got {order!r}")
        if int(step_deg) != step_deg or step_deg < 1:
            raise ValueError(f"oracle: step_deg must be a positive integer, got {step_deg!r}")
        self.order = order
        self.pitch_bound = int(pitch_bound)
        self.step = int(step_deg)
        n = self.num_envs
        self.pitch = np.zeros(n, dtype=np.int64)  # dead-reckoned rotation, degrees
        self.yaw = np.zeros(n, dtype=np.int64)
        self.target_pitch = np.zeros(n, dtype=np.int64)
        self.target_yaw = np.zeros(n, dtype=np.int64)
        self.has_episode = np.zeros(n, dtype=bool)
        self.done = np.zeros(n, dtype=bool)

    @classmethod
    def from_config(cls, cfg: "OracleAgentConfig", num_envs: int, device: str | torch.device, seed: int) -> "OracleAgent":
        """Factory for :func:`~findview_baselines.agents.make_agent` from the typed ``agent`` section."""
        return cls(num_envs, device, seed, order=cfg.order, pitch_bound=cfg.pitch_bound, step_deg=cfg.step_deg)

    @light_work()
    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        super().reset(env_ids, episodes)
        for i, ep in zip(env_ids, episodes):
            if ep is None:
                self.has_episode[i] = False
                self.done[i] = True
                continue
            self.pitch[i], self.yaw[i] = int(ep.init_pitch), int(ep.init_yaw)
            self.target_pitch[i], self.target_yaw[i] = int(ep.target_pitch), int(ep.target_yaw)
            self.has_episode[i] = True
            self.done[i] = False

    def next_actions(self) -> np.ndarray:
        """The shortest-path action of every slot ``(N,)`` int64, without moving (no side effects)."""
        dp = self.target_pitch - self.pitch
        dy = wrap_yaw(self.target_yaw - self.yaw)  # in (-180, 180]: the short way round (+180: right)
        pitch_move = np.where(dp > 0, UP, DOWN)
        yaw_move = np.where(dy > 0, RIGHT, LEFT)
        need_p = np.abs(dp) >= self.step
        need_y = np.abs(dy) >= self.step
        if self.order == "pitch_first":
            a = np.where(need_p, pitch_move, np.where(need_y, yaw_move, STOP))
        else:
            a = np.where(need_y, yaw_move, np.where(need_p, pitch_move, STOP))
        return np.where(self.done | ~self.has_episode, STOP, a).astype(np.int64)

    @light_work()
    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, _ = self._check_obs(obs)
        missing = np.flatnonzero(~self.has_episode & ~self.done).tolist()
        if missing:
            raise RuntimeError(f"oracle: slots {missing} were never reset with an Episode")
        a = self.next_actions()
        # dead-reckon with the environment's rules
        self.pitch = np.clip(
            self.pitch + self.step * ((a == UP).astype(np.int64) - (a == DOWN)), -self.pitch_bound, self.pitch_bound
        )
        self.yaw = wrap_yaw(self.yaw + self.step * ((a == RIGHT).astype(np.int64) - (a == LEFT)))
        self.done |= a == STOP
        return self._as_actions(a, view.device)
