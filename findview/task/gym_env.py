"""A single-episode FindView environment following the Gymnasium API.

``reset(seed=...) -> (obs, info)``, ``step(a) -> (obs, reward, terminated, truncated, info)`` with
``terminated`` = the agent called STOP and ``truncated`` = forced stop at ``max_steps``. Observations are
``{"view": (H, W, 3) uint8, "target": (H, W, 3) uint8}`` numpy arrays (RGB). Requires the optional
``gymnasium`` package (``pip install 'findview[gym]'``).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from findview.episode import Episode
from findview.sim.simulator import Simulator
from findview.task.actions import ACTION_NAMES, NUM_ACTIONS
from findview.task.env import FindViewEnv
from findview.task.rewards import RewardConfig

try:  # optional dependency
    import gymnasium as gym
    from gymnasium import spaces

    _Base = gym.Env
except ImportError:  # pragma: no cover - exercised when gymnasium is absent
    gym = None
    spaces = None
    _Base = object


class _OneShotSource:
    """Feeds exactly the episode chosen by ``reset``."""

    def __init__(self) -> None:
        self.episode: Episode | None = None

    def next(self) -> Episode | None:
        ep, self.episode = self.episode, None
        return ep

    def peek(self, n: int) -> list[Episode]:
        return []


class FindViewGymEnv(_Base):
    """One FindView episode at a time, Gymnasium-style.

    Args:
        simulator: the renderer.
        episodes: a fixed list to cycle through (``reset(seed=s)`` picks one at random, seeded;
            ``options={"episode": ep}`` picks one explicitly), or
        sampler: an object with ``sample(difficulty) -> Episode`` (re-seeded by ``reset(seed=...)``
            when it has ``reseed(seed)``).
        difficulty: the difficulty drawn from the sampler.
        max_steps, pitch_bound, reward: as :class:`~findview.task.env.FindViewEnv`.
    """

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(
        self,
        simulator: Simulator,
        episodes: Sequence[Episode] | None = None,
        sampler: Any = None,
        difficulty: str = "easy",
        max_steps: int = 5000,
        pitch_bound: int = 60,
        reward: RewardConfig | None = None,
    ) -> None:
        if gym is None:
            raise ImportError("FindViewGymEnv needs gymnasium: pip install 'findview[gym]' (or pip install gymnasium)")
        if not episodes and sampler is None:
            raise ValueError("FindViewGymEnv needs a non-empty list of episodes or a sampler")
        self._episodes = list(episodes or [])
        self._cursor = 0
        self._sampler = sampler
        self._difficulty = difficulty
        self._source = _OneShotSource()
        self._env = FindViewEnv(
            simulator, self._source, 1, max_steps=max_steps, pitch_bound=pitch_bound, reward=reward, auto_reset=False
        )
        h, w = simulator.height, simulator.width
        img = spaces.Box(0, 255, (h, w, 3), np.uint8)
        self.observation_space = spaces.Dict({"view": img, "target": img})
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self.action_names = ACTION_NAMES
        self._running = False

    def _obs(self) -> dict[str, np.ndarray]:
        o = self._env.observations
        return {k: np.ascontiguousarray(o[k][0].permute(1, 2, 0).cpu().numpy()) for k in ("view", "target")}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if options and "episode" in options:
            ep = options["episode"]
        elif self._sampler is not None:
            if seed is not None and hasattr(self._sampler, "reseed"):
                self._sampler.reseed(seed)
            ep = self._sampler.sample(self._difficulty)
        else:
            if seed is not None:
                self._cursor = int(self.np_random.integers(len(self._episodes)))
            ep = self._episodes[self._cursor % len(self._episodes)]
            self._cursor += 1
        self._source.episode = ep
        self._env.reset_envs([0])
        self._running = True
        return self._obs(), {"episode": ep}

    def step(self, action):
        if not self._running:
            raise RuntimeError("the episode has ended (or never started): call reset() before step()")
        _, reward, done, infos = self._env.step(torch.tensor([int(action)]))
        info: dict[str, Any] = {}
        terminated = truncated = False
        if bool(done[0]):
            self._running = False
            info = dict(infos[0])
            terminated = bool(info["called_stop"])
            truncated = not terminated
        return self._obs(), float(reward[0]), terminated, truncated, info

    def render(self):
        return self._obs()["view"]

    def close(self) -> None:
        self._env.close()
