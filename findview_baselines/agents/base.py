"""The batched agent interface shared by every baseline, plus small helpers.

Contract (docs/ARCHITECTURE.md):

- ``Agent.reset(env_ids, episodes)`` is called when the slots ``env_ids`` start the episodes ``episodes``
  (the observation returned with ``env.new_episode[i] == True``), before ``act`` sees that observation;
- ``Agent.act(obs) -> (N,) long`` on the device of ``obs["view"]``; ``obs = {"view", "target"}`` are
  ``(N, 3, H, W)`` uint8 RGB tensors. Actions: UP=0, DOWN=1, LEFT=2, RIGHT=3, STOP=4;
- optionally ``Agent.step_stop_prob() -> (N,) float | None``: the STOP probability behind the last ``act``
  (for per-step traces; ``None`` by default, the learned agent gives its policy's).

Only the oracle may use the rotations stored in an :class:`~findview.episode.Episode`. The other agents
read nothing from it but its ``difficulty`` (the rule-based agents tune ``d_thresh`` per difficulty, as
in the paper) and its identity (``episode_id``/``seed``, to seed their per-episode randomness so an
episode's trajectory does not depend on which slot or batch it ran in).

A slot whose agent answered STOP keeps answering STOP (without any work) until it is reset: inactive
slots of an exhausted static source cost nothing. ``reset`` with a ``None`` episode idles a slot the same
way (e.g. a slot whose episode was force-stopped at ``T`` and whose source is exhausted).
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import torch

from findview.episode import Episode
from findview.task import ACTION_NAMES, NUM_ACTIONS, Action

UP, DOWN, LEFT, RIGHT, STOP = (int(Action.UP), int(Action.DOWN), int(Action.LEFT), int(Action.RIGHT), int(Action.STOP))

#: config keys every agent accepts and ignores (set by the Hydra group files / tools)
GENERIC_KEYS = frozenset({"name", "_target_", "description"})

__all__ = [
    "Action",
    "UP",
    "DOWN",
    "LEFT",
    "RIGHT",
    "STOP",
    "NUM_ACTIONS",
    "ACTION_NAMES",
    "Agent",
    "to_plain_dict",
    "check_keys",
    "episode_rng",
    "rgb_to_gray",
    "host_images",
    "chw_to_hwc",
    "gray_of",
]


def to_plain_dict(cfg: Any) -> dict[str, Any]:
    """A config (``None``, mapping or OmegaConf ``DictConfig``) as a plain, resolved ``dict``."""
    if cfg is None:
        return {}
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return dict(OmegaConf.to_container(cfg, resolve=True))  # type: ignore[arg-type]
    except ImportError:  # pragma: no cover
        pass
    if isinstance(cfg, Mapping):
        return dict(cfg)
    raise TypeError(f"agent config must be a mapping or a DictConfig, got {type(cfg).__name__}")


def check_keys(agent: str, cfg: Mapping[str, Any], allowed: Sequence[str]) -> None:
    """Raise ``ValueError`` naming the unknown keys of ``cfg`` (typos in overrides fail loudly)."""
    unknown = sorted(set(cfg) - set(allowed) - GENERIC_KEYS)
    if unknown:
        raise ValueError(f"agent {agent!r}: unknown config keys {unknown}; valid keys: {sorted(allowed)}")


def episode_rng(seed: int, episode: Episode | None, fallback: np.random.Generator) -> np.random.Generator:
    """A numpy generator for one episode, derived from the agent seed and the episode's identity.

    The same (seed, episode) always gives the same stream, whatever slot or batch it runs in. Without an
    episode a child of ``fallback`` is used.
    """
    if episode is None:
        return np.random.default_rng(fallback.integers(0, 2**63 - 1))
    ident = zlib.crc32(str(episode.episode_id).encode("utf-8"))
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, int(episode.seed) & 0xFFFFFFFF, ident])


def host_images(images: torch.Tensor, index: Sequence[int] | None = None) -> np.ndarray:
    """``(N, 3, H, W)`` uint8 tensor (any device) -> ``(K, 3, H, W)`` uint8 numpy array of the rows ``index``.

    One host transfer per call: a CPU tensor is viewed without a copy (``Tensor.numpy()``) and indexed
    in numpy; a CUDA tensor is indexed on its device and copied once. No torch op runs on the host, so
    a busy CPU cannot make this call wait on idle OpenMP threads (docs/ARCHITECTURE.md, CPU threads).
    """
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"expected (N, 3, H, W) RGB images, got shape {tuple(images.shape)}")
    if images.device.type == "cpu":
        arr = images.detach().numpy()
        return arr if index is None else arr[np.asarray(index, dtype=np.int64)]
    if index is not None:
        images = images[torch.as_tensor(list(index), dtype=torch.long, device=images.device)]
    return images.detach().cpu().numpy()


def chw_to_hwc(image: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` -> contiguous ``(H, W, 3)`` (the layout OpenCV expects); one copy."""
    return np.ascontiguousarray(image.transpose(1, 2, 0))


def gray_of(image: np.ndarray) -> np.ndarray:
    """``(3, H, W)`` uint8 RGB numpy image -> ``(H, W)`` uint8 gray, ``0.299 R + 0.587 G + 0.114 B`` in
    OpenCV's 14-bit fixed point (``(4899 R + 9617 G + 1868 B + 8192) >> 14``, the reference rounding of
    ``cv2.cvtColor(..., COLOR_RGB2GRAY)``; its SIMD path differs by 1 on ~0.3% of the pixels), in numpy."""
    r = image[0].astype(np.uint32)
    r *= 4899
    r += image[1].astype(np.uint32) * 9617
    r += image[2].astype(np.uint32) * 1868
    r += 8192
    r >>= 14
    return r.astype(np.uint8)


def rgb_to_gray(images: torch.Tensor) -> np.ndarray:
    """``(N, 3, H, W)`` uint8 RGB tensor (any device) -> ``(N, H, W)`` uint8 numpy gray images.

    :func:`gray_of` on one host copy of the batch (:func:`host_images`); no torch op runs on the host.
    """
    arr = host_images(images)
    if arr.shape[0] == 0:
        return np.zeros((0,) + arr.shape[2:], np.uint8)
    return np.stack([gray_of(a) for a in arr])


class Agent:
    """Base class of the batched agents.

    Args:
        num_envs: number of environment slots ``N``.
        device: device of the returned actions when ``act`` cannot infer it (normally the obs device).
        seed: seed of all the agent's randomness.
    """

    name = "agent"

    def __init__(self, num_envs: int, device: str | torch.device = "cpu", seed: int = 0) -> None:
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = int(num_envs)
        self.device = torch.device(device) if not isinstance(device, torch.device) else device
        self.seed = int(seed)

    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        """Slots ``env_ids`` start ``episodes`` (same length) at the next observation."""
        if len(env_ids) != len(episodes):
            raise ValueError(f"reset: {len(env_ids)} env ids but {len(episodes)} episodes")
        for i in env_ids:
            if not 0 <= int(i) < self.num_envs:
                raise IndexError(f"reset: env id {i} out of range for {self.num_envs} envs")

    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Next actions ``(N,)`` long on the device of ``obs["view"]``."""
        raise NotImplementedError

    def step_stop_prob(self) -> torch.Tensor | None:
        """How sure the agent was about STOP in its last :meth:`act`, for per-step traces (``tools/eval.py
        trace=true``): ``(N,)`` float probabilities in ``[0, 1]`` (any device), ``NaN`` for the slots where no
        model decided that step; ``None`` (this default) for an agent without such a probability (the rule-based
        ones). Called only by whoever wants it (a trace recorder), after ``act``: an agent keeps what it needs
        for the answer without copying it to the host, so ``act`` costs nothing more when no one asks."""
        return None

    # helpers -----------------------------------------------------------------------------------
    def _check_obs(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        try:
            view, target = obs["view"], obs["target"]
        except KeyError as e:
            raise KeyError(f"{self.name}: observation lacks {e}; expected keys 'view' and 'target'") from e
        if view.ndim != 4 or view.shape != target.shape:
            raise ValueError(
                f"{self.name}: view {tuple(view.shape)} and target {tuple(target.shape)} must both be (N, 3, H, W)"
            )
        if view.shape[0] != self.num_envs:
            raise ValueError(f"{self.name}: got {view.shape[0]} observations for {self.num_envs} envs")
        if view.dtype != torch.uint8 or target.dtype != torch.uint8:
            raise TypeError(f"{self.name}: observations must be uint8, got {view.dtype} / {target.dtype}")
        return view, target

    def _as_actions(self, actions: Sequence[int] | np.ndarray, device: torch.device) -> torch.Tensor:
        return torch.as_tensor(np.asarray(actions, dtype=np.int64), device=device)
