"""Views rendered larger than the network takes them: area averaging, for acting and for training.

A learned agent whose network takes ``H x W`` images (64 x 64 in the CPU recipe) can work from views the
simulator renders at ``k H x k W`` (256 x 256, the size every rule-based agent sees): each ``k x k`` block
is averaged, the way a camera image is resized. This matters for corrupted targets. A corruption's
kernel is in pixels of the image it is applied to, so a target corrupted at 64 x 64 loses four times
more of its picture than the same severity applied at 256 x 256; rendering at 256 and averaging down
gives the learned agent the same corrupted target as every other agent.

- :func:`area_downsample` / :func:`downsample_factor`: the operation and the size check;
- :class:`DownsampledEnv`: a training environment whose observations come averaged down (``agent.downsample``).

Identical inputs give identical outputs, so a clean target still matches its view exactly.
"""

from __future__ import annotations

from typing import Any

import torch

__all__ = ["area_downsample", "downsample_factor", "DownsampledEnv"]


def downsample_factor(size: tuple[int, int], network: tuple[int, int]) -> int | None:
    """The integer ``k >= 1`` with ``size == (k * network[0], k * network[1])`` (``(height, width)`` pixels),
    else ``None``."""
    k = int(size[0]) // int(network[0])
    return k if k >= 1 and (int(size[0]), int(size[1])) == (k * network[0], k * network[1]) else None


def area_downsample(images: torch.Tensor, k: int) -> torch.Tensor:
    """``(N, 3, k H, k W)`` uint8 -> ``(N, 3, H, W)`` uint8: the mean of each ``k x k`` block, rounded to the
    nearest grey level, a tie to the even one (1.5 -> 2, 2.5 -> 2; ``k = 1``: the images themselves, not
    copied). Any device; the block sums are exact in float32, so CPU and CUDA give the same bytes."""
    if k == 1:
        return images
    return torch.nn.functional.avg_pool2d(images.float(), k).round_().to(torch.uint8)


class DownsampledEnv:
    """A :class:`~findview.task.FindViewEnv` whose observations (``reset``, ``reset_envs``, ``step``,
    ``load_state_dict``, ``view`` / ``target``) are :func:`area_downsample`-d by ``k``; everything else (poses,
    episodes, the simulator, state for checkpoints) is the wrapped environment's.

    Args:
        env: the environment, rendering ``k H x k W`` views.
        k: the averaging factor (>= 2; the network takes ``H x W``).
    """

    def __init__(self, env: Any, k: int) -> None:
        if int(k) < 2:
            raise ValueError(f"DownsampledEnv needs a factor >= 2, got {k!r}")
        self.env, self.k = env, int(k)

    def _obs(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {key: area_downsample(value, self.k) for key, value in obs.items()}

    def reset(self) -> dict[str, torch.Tensor]:
        return self._obs(self.env.reset())

    def reset_envs(self, env_ids: list[int]) -> dict[str, torch.Tensor]:
        return self._obs(self.env.reset_envs(env_ids))

    def step(self, actions: torch.Tensor):
        obs, rewards, done, infos = self.env.step(actions)
        return self._obs(obs), rewards, done, infos

    def load_state_dict(self, state: dict) -> dict[str, torch.Tensor]:
        return self._obs(self.env.load_state_dict(state))

    @property
    def observations(self) -> dict[str, torch.Tensor]:
        return self._obs(self.env.observations)

    @property
    def view(self) -> torch.Tensor:
        return area_downsample(self.env.view, self.k)

    @property
    def target(self) -> torch.Tensor:
        return area_downsample(self.env.target, self.k)

    def __getattr__(self, name: str) -> Any:  # poses, episodes, sim, num_envs, device, state_dict, ...
        if name == "env":  # not set yet (a copy or unpickling before __init__): no endless recursion
            raise AttributeError(name)
        return getattr(self.env, name)
