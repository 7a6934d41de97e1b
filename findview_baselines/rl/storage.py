"""Rollout storage for recurrent PPO: preallocated tensors, GAE, recurrent mini-batches.

Index conventions (``T`` = rollout steps, ``N`` = environments)::

    step t:   inputs  obs[t], hidden[t], masks[t]      (what the policy saw / the state entering step t)
              outputs actions[t], log_probs[t], values[t]
              result  rewards[t], and obs[t+1], masks[t+1] returned by env.step(actions[t])

Optional auxiliary targets: ``aux_targets[t]`` (N, 3) are the privileged rotation labels of ``obs[t]``
(``findview.task.oracle.rotation_labels(env)`` computed *before* ``env.step``); they reach the
mini-batches only when every step of the rollout got them.

``masks[t] == 0`` means ``obs[t]`` starts a new episode (with an auto-resetting env this is the same as
"the episode ended at step t-1"), so GAE does not bootstrap across it and the GRU state is zeroed there.
Index ``T`` of obs / hidden / masks / values holds the state after the last step; ``after_update``
moves it to index 0 for the next rollout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator, Mapping

import torch

AUX_SIZE = 3  # (dpitch / fov, dyaw / fov, overlap): findview.task.oracle.rotation_labels


@dataclass
class MiniBatch:
    """A set of whole environment sequences, time-major and flattened (``n`` envs, ``T`` steps).

    view, target: (T*n, 3, H, W) uint8; hidden0: (n, hidden); masks, actions, old_log_probs, old_values,
    returns, advantages: (T*n,); env_ids: (n,) which environments (columns of the storage) these are;
    aux_targets: (T*n, 3) rotation labels, or ``None`` when the rollout was stored without them.
    """

    env_ids: torch.Tensor
    view: torch.Tensor
    target: torch.Tensor
    hidden0: torch.Tensor
    masks: torch.Tensor
    actions: torch.Tensor
    old_log_probs: torch.Tensor
    old_values: torch.Tensor
    returns: torch.Tensor
    advantages: torch.Tensor
    aux_targets: torch.Tensor | None = None

    @property
    def obs(self) -> dict[str, torch.Tensor]:
        return {"view": self.view, "target": self.target}


class RolloutStorage:
    """Preallocated rollout buffers for ``num_steps`` steps of ``num_envs`` environments on ``device``.

    Memory: the two uint8 image buffers take ``2 * (T+1) * N * 3 * H * W`` bytes (about 0.8 GB for the
    paper's 128 x 16 x 256x256).
    """

    def __init__(
        self,
        num_steps: int,
        num_envs: int,
        height: int,
        width: int,
        hidden_size: int,
        device: torch.device | str = "cpu",
    ) -> None:
        self.num_steps = num_steps
        self.num_envs = num_envs
        self.device = torch.device(device)
        T, N = num_steps, num_envs
        kw = {"device": self.device}
        self.view = torch.zeros(T + 1, N, 3, height, width, dtype=torch.uint8, **kw)
        self.target = torch.zeros(T + 1, N, 3, height, width, dtype=torch.uint8, **kw)
        self.hidden = torch.zeros(T + 1, N, hidden_size, **kw)
        self.masks = torch.zeros(T + 1, N, **kw)  # 0 at step 0 of a fresh run: every episode starts there
        self.actions = torch.zeros(T, N, dtype=torch.long, **kw)
        self.log_probs = torch.zeros(T, N, **kw)
        self.values = torch.zeros(T + 1, N, **kw)  # values[T] = bootstrap value, set by compute_returns
        self.rewards = torch.zeros(T, N, **kw)
        self.returns = torch.zeros(T, N, **kw)
        self.aux_targets = torch.zeros(T, N, AUX_SIZE, **kw)
        self.aux_valid = torch.zeros(T, dtype=torch.bool)  # which steps got aux targets (CPU flags)
        self.step = 0

    # ---------------------------------------------------------------------------------------------
    # Filling
    # ---------------------------------------------------------------------------------------------

    def set_initial(self, obs: Mapping[str, torch.Tensor], masks: torch.Tensor | None = None) -> None:
        """Store the first observation (after ``env.reset()``): zero state, masks 0 unless given (N,)."""
        self.view[0].copy_(obs["view"])
        self.target[0].copy_(obs["target"])
        self.hidden[0].zero_()
        if masks is None:
            self.masks[0].zero_()
        else:
            self.masks[0].copy_(masks)
        self.step = 0

    def current(self) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        """Policy inputs of the current step: obs dict (N, 3, H, W), hidden (N, hidden), masks (N,)."""
        t = self.step
        return {"view": self.view[t], "target": self.target[t]}, self.hidden[t], self.masks[t]

    def insert(
        self,
        next_obs: Mapping[str, torch.Tensor],
        next_hidden: torch.Tensor,
        actions: torch.Tensor,
        log_probs: torch.Tensor,
        values: torch.Tensor,
        rewards: torch.Tensor,
        next_masks: torch.Tensor,
        aux_targets: torch.Tensor | None = None,
    ) -> None:
        """Record one step: what the policy output at step t and what the env returned.

        Args:
            next_obs: {"view", "target"} (N, 3, H, W) uint8 returned by ``env.step``.
            next_hidden: (N, hidden) GRU state after step t (from ``policy.act``).
            actions, log_probs, values: (N,) from ``policy.act`` at step t.
            rewards: (N,) reward of step t.
            next_masks: (N,) 0 where ``next_obs`` starts a new episode (``~env.new_episode``).
            aux_targets: optional (N, 3) rotation labels of the observation acted on at step t (the one
                from :meth:`current`), i.e. ``rotation_labels(env)`` taken before ``env.step``.
        """
        if self.step >= self.num_steps:
            raise IndexError(f"rollout storage is full ({self.num_steps} steps); call after_update()")
        t = self.step
        self.actions[t].copy_(actions)
        self.log_probs[t].copy_(log_probs)
        self.values[t].copy_(values)
        self.rewards[t].copy_(rewards)
        self.view[t + 1].copy_(next_obs["view"])
        self.target[t + 1].copy_(next_obs["target"])
        self.hidden[t + 1].copy_(next_hidden)
        self.masks[t + 1].copy_(next_masks)
        if aux_targets is not None:
            self.aux_targets[t].copy_(aux_targets)
        self.aux_valid[t] = aux_targets is not None
        self.step = t + 1

    @property
    def has_aux_targets(self) -> bool:
        """Whether every step of the (full) rollout was inserted with ``aux_targets``."""
        return bool(self.aux_valid.all())

    def after_update(self) -> None:
        """Carry the last observation / state / mask over to index 0 for the next rollout."""
        self.view[0].copy_(self.view[-1])
        self.target[0].copy_(self.target[-1])
        self.hidden[0].copy_(self.hidden[-1])
        self.masks[0].copy_(self.masks[-1])
        self.aux_valid.zero_()
        self.step = 0

    def state_dict(self) -> dict[str, torch.Tensor]:
        """What a resumed run needs: the rollout's starting observation, GRU state and masks (index 0; the
        rest of the buffer is refilled by the next rollout). CPU tensors, loadable with ``weights_only``."""
        return {
            "view": self.view[0].cpu().clone(),
            "target": self.target[0].cpu().clone(),
            "hidden": self.hidden[0].cpu().clone(),
            "masks": self.masks[0].cpu().clone(),
        }

    def load_state_dict(self, state: Mapping[str, torch.Tensor]) -> None:
        """Restore :meth:`state_dict`; the next rollout starts from it."""
        self.view[0].copy_(state["view"])
        self.target[0].copy_(state["target"])
        self.hidden[0].copy_(state["hidden"])
        self.masks[0].copy_(state["masks"])
        self.aux_valid.zero_()
        self.step = 0

    # ---------------------------------------------------------------------------------------------
    # Returns and advantages
    # ---------------------------------------------------------------------------------------------

    @torch.no_grad()
    def compute_returns(self, next_value: torch.Tensor, gamma: float, lam: float) -> torch.Tensor:
        """Generalised advantage estimation; fills ``self.returns`` (T, N) and returns the advantages (T, N).

        ``next_value`` (N,) is the critic's value of ``obs[T]``. For every step t (backwards)::

            not_done = masks[t+1]        # 0 if the episode ended at step t
            delta_t  = rewards[t] + gamma * values[t+1] * not_done - values[t]
            A_t      = delta_t + gamma * lam * not_done * A_{t+1}
            returns[t] = A_t + values[t]
        """
        self.values[-1].copy_(next_value)
        advantages = torch.zeros_like(self.rewards)
        next_advantage = torch.zeros_like(next_value, dtype=self.rewards.dtype)
        for t in reversed(range(self.num_steps)):
            not_done = self.masks[t + 1]
            delta = self.rewards[t] + gamma * self.values[t + 1] * not_done - self.values[t]
            next_advantage = delta + gamma * lam * not_done * next_advantage
            advantages[t] = next_advantage
        self.returns.copy_(advantages + self.values[:-1])
        return advantages

    # ---------------------------------------------------------------------------------------------
    # Mini-batches
    # ---------------------------------------------------------------------------------------------

    def recurrent_minibatches(
        self,
        advantages: torch.Tensor,
        num_mini_batches: int,
        generator: torch.Generator | None = None,
    ) -> Iterator[MiniBatch]:
        """Split the environments (not the time axis) into ``num_mini_batches`` shuffled groups.

        Each env lands in exactly one mini-batch per call, and keeps its whole ``T``-step sequence so that
        ``policy.evaluate_actions`` can re-run the GRU from ``hidden[0]``.

        Args:
            advantages: (T, N), usually normalised by the PPO update.
            num_mini_batches: 1..N (1 = all envs at once, the paper's setting).
            generator: optional CPU generator for a reproducible env shuffle.
        """
        N = self.num_envs
        if not 1 <= num_mini_batches <= N:
            raise ValueError(
                f"num_mini_batches must be in [1, {N}] (at least one env per mini-batch), got {num_mini_batches}"
            )
        order = torch.randperm(N, generator=generator).to(self.device)
        T = self.num_steps
        with_aux = self.has_aux_targets
        for env_ids in order.tensor_split(num_mini_batches):

            def take(x: torch.Tensor) -> torch.Tensor:
                """(T, N, ...) -> (T * n, ...) for the selected envs, time-major."""
                return x[:T, env_ids].flatten(0, 1)

            yield MiniBatch(
                env_ids=env_ids,
                view=take(self.view),
                target=take(self.target),
                hidden0=self.hidden[0, env_ids],
                masks=take(self.masks),
                actions=take(self.actions),
                old_log_probs=take(self.log_probs),
                old_values=take(self.values),
                returns=take(self.returns),
                advantages=advantages[:, env_ids].flatten(0, 1),
                aux_targets=take(self.aux_targets) if with_aux else None,
            )
