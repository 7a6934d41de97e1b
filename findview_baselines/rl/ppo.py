"""PPO update (clipped surrogate, clipped value loss, entropy bonus) with linear lr / clip decay.

The loss of one mini-batch, with ``ratio = exp(log_pi_new(a) - log_pi_old(a))`` and normalised
advantages ``A``::

    policy_loss = -mean(min(ratio * A, clamp(ratio, 1 - clip, 1 + clip) * A))
    v_clipped   = old_v + clamp(v - old_v, -clip, clip)
    value_loss  = 0.5 * mean(max((v - R)^2, (v_clipped - R)^2))     (0.5 * mean((v - R)^2) if not clipped)
    loss        = policy_loss + value_coef * value_loss - entropy_coef * mean(entropy)
                  (+ aux_coef * aux_loss when ``aux_coef > 0``: see ``policy.aux_loss``)
                  (+ kl_to_init_coef * KL(pi_init || pi) when ``kl_to_init_coef > 0``: the frozen starting policy
                   pi_init runs on the same chunks from the same initial GRU state)

With ``aux_coef > 0`` an :class:`~findview_baselines.rl.policy.AuxHead` on the policy's pre-GRU features
is trained alongside (it belongs to :class:`PPO`, is saved in its ``state_dict`` and never in the policy
weights); every rollout must then be stored with ``aux_targets=rotation_labels(env)``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Mapping

import torch
from torch import nn

from findview.config import check
from findview.runtime import scoped
from findview_baselines.rl import distributed
from findview_baselines.rl.aux_head import AuxHead, aux_loss
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.storage import RolloutStorage


def linear_decay(initial: float, update: int, total_updates: int) -> float:
    """``initial * (1 - update / total_updates)``, floored at 0 (update 0 -> ``initial``)."""
    if total_updates <= 0:
        return initial
    return initial * max(0.0, 1.0 - update / total_updates)


@dataclass
class PPOConfig:
    """PPO hyper-parameters: the ``trainer.ppo`` config section (``trainer=ppo``; the network and how it acts
    are the ``agent`` section, :class:`findview_baselines.config.PPOAgentConfig`). Validated on construction."""

    lr: float = 2.5e-4
    """Adam learning rate."""
    adam_eps: float = 1e-5
    """Adam's epsilon (numerical floor of the denominator), not the localization error."""
    clip: float = 0.2
    """PPO ratio clip (also the value-loss clip)."""
    value_coef: float = 0.5
    """Value-loss weight."""
    entropy_coef: float = 0.01
    """Entropy-bonus weight."""
    max_grad_norm: float = 0.5
    """Gradient-norm clip."""
    gamma: float = 0.99
    """Discount per step."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    ppo_epochs: int = 4
    """Passes over each rollout."""
    num_mini_batches: int = 1
    """Mini-batches per epoch (they split environments, so at most trainer.num_envs)."""
    rollout_steps: int = 128
    """Steps per environment per update."""
    linear_decay: bool = True
    """Decay lr and clip linearly to 0 over the run."""
    clipped_value_loss: bool = True
    """Clip the value loss like the policy ratio."""
    normalize_advantage: bool = True
    """Normalise advantages (mean / std of the whole rollout, over all ranks under torchrun)."""
    aux_coef: float = 0.0
    """Weight of the auxiliary loss (relative rotation regression + overlap classification); 0 = off (the
    paper's recipe)."""
    kl_to_init_coef: float = 0.0
    """Weight of ``KL(pi_init || pi)`` on the rollout's states, where ``pi_init`` is a frozen copy of the policy
    as the run's first update found it (the ``init_from`` imitation policy): keeps fine-tuning near the policy
    it starts from. 0 = off (the paper's recipe)."""
    critic_warmup_updates: int = 0
    """For this many first updates of a run only the critic's output layer learns (the actor, the GRU and the
    encoder are frozen): a fine-tuning run (``init_from`` an imitation checkpoint) then starts its policy
    updates with a value function fitted to the inherited policy instead of advantages from a random critic.
    0 = off."""

    def __post_init__(self) -> None:
        for name in ("lr", "adam_eps", "rollout_steps", "ppo_epochs", "num_mini_batches"):
            check(getattr(self, name) > 0, f"trainer.ppo.{name}", getattr(self, name), "a positive number")
        check(0 < self.gamma <= 1, "trainer.ppo.gamma", self.gamma, "a discount in (0, 1]")
        for name in ("aux_coef", "kl_to_init_coef", "critic_warmup_updates"):
            check(getattr(self, name) >= 0, f"trainer.ppo.{name}", getattr(self, name), "0 (off) or a positive number")


def ppo_loss(
    log_probs: torch.Tensor,
    old_log_probs: torch.Tensor,
    advantages: torch.Tensor,
    values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    entropy: torch.Tensor,
    clip: float,
    value_coef: float,
    entropy_coef: float,
    clipped_value_loss: bool = True,
) -> dict[str, torch.Tensor]:
    """The PPO loss of one mini-batch; every input is (B,). Returns scalar tensors.

    Keys: ``loss`` (to minimise), ``policy_loss``, ``value_loss``, ``entropy``, ``approx_kl``
    (``mean((ratio - 1) - log ratio)``, an unbiased, non-negative KL(old || new) estimate) and
    ``clip_fraction`` (share of samples with ``|ratio - 1| > clip``). The last two carry no gradient.
    """
    log_ratio = log_probs - old_log_probs
    ratio = log_ratio.exp()
    surrogate = ratio * advantages
    surrogate_clipped = ratio.clamp(1.0 - clip, 1.0 + clip) * advantages
    policy_loss = -torch.min(surrogate, surrogate_clipped).mean()

    if clipped_value_loss:
        values_clipped = old_values + (values - old_values).clamp(-clip, clip)
        value_loss = 0.5 * torch.max((values - returns).pow(2), (values_clipped - returns).pow(2)).mean()
    else:
        value_loss = 0.5 * (values - returns).pow(2).mean()

    entropy = entropy.mean()
    loss = policy_loss + value_coef * value_loss - entropy_coef * entropy

    with torch.no_grad():
        approx_kl = ((ratio - 1.0) - log_ratio).mean()
        clip_fraction = ((ratio - 1.0).abs() > clip).float().mean()
    return {
        "loss": loss,
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": entropy,
        "approx_kl": approx_kl,
        "clip_fraction": clip_fraction,
    }


def _check_finite(terms: Mapping[str, torch.Tensor]) -> None:
    """Raise ``FloatingPointError`` listing every non-finite loss term (called before the optimizer step)."""
    bad = [f"{name}={value.item()}" for name, value in terms.items() if not torch.isfinite(value).all()]
    if bad:
        raise FloatingPointError("non-finite PPO loss terms: " + ", ".join(bad))


class PPO:
    """PPO optimiser for a :class:`Policy`.

    Usage per update (see ``ppo_trainer.py``)::

        ppo.set_progress(update, total_updates)      # linear decay of lr and clip
        storage.compute_returns(next_value, cfg.gamma, cfg.gae_lambda)
        stats = ppo.update(storage)                  # may raise FloatingPointError
    """

    def __init__(self, policy: Policy, cfg: PPOConfig) -> None:
        self.policy = policy
        self.cfg = cfg
        self.aux_head: AuxHead | None = None
        params = list(policy.parameters())
        if cfg.aux_coef > 0:
            self.aux_head = AuxHead(policy.feature_size).to(next(policy.parameters()).device)
            params += list(self.aux_head.parameters())
        self.params = params
        self.optimizer = torch.optim.Adam(params, lr=cfg.lr, eps=cfg.adam_eps)
        self.lr = cfg.lr
        self.clip = cfg.clip
        self.progress_update = 0  # the update being made (set_progress), for the critic warm-up
        critic = {id(p) for p in policy.critic.parameters()}
        self.frozen_in_warmup = [p for p in params if id(p) not in critic]
        self.init_policy: Policy | None = None  # frozen copy, made at the first update (after init_from)

    def _frozen_copy(self, state: Mapping[str, torch.Tensor] | None = None) -> Policy:
        anchor = copy.deepcopy(self.policy)
        if state is not None:
            anchor.load_state_dict(state)
        anchor.eval()
        for p in anchor.parameters():
            p.requires_grad_(False)
        return anchor

    def set_progress(self, update: int, total_updates: int) -> None:
        """Set lr and clip for update ``update`` out of ``total_updates`` (constant if linear_decay is off)."""
        self.progress_update = int(update)
        if self.cfg.linear_decay:
            self.lr = linear_decay(self.cfg.lr, update, total_updates)
            self.clip = linear_decay(self.cfg.clip, update, total_updates)
        else:
            self.lr, self.clip = self.cfg.lr, self.cfg.clip
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr

    @scoped(lambda self: self.policy.heavy)
    def update(self, storage: RolloutStorage, generator: torch.Generator | None = None) -> dict[str, float]:
        """``ppo_epochs`` passes over the rollout in ``num_mini_batches`` env groups.

        ``storage.compute_returns`` must have been called. Returns the mean over all mini-batches of
        ``policy_loss, value_loss, entropy, approx_kl, clip_fraction, grad_norm`` (pre-clipping norm),
        plus the ``lr`` and ``clip`` in use (and ``aux_loss, aux_rotation_loss, aux_overlap_accuracy``
        with ``aux_coef > 0``; then a storage without aux targets raises ``ValueError``). Raises
        ``FloatingPointError`` (before stepping the optimizer)
        if the loss or the gradient norm is not finite.
        """
        cfg = self.cfg
        steps = storage.num_steps  # all rows, unless a preempted rollout is shorter (see ppo_trainer)
        advantages = storage.returns[:steps] - storage.values[:steps]
        if cfg.normalize_advantage:
            # statistics of the whole batch: over every rank's environments under torchrun
            mean, std = distributed.mean_std(advantages)
            advantages = (advantages - mean) / (std + 1e-5)

        if self.aux_head is not None and not storage.has_aux_targets:
            raise ValueError(
                "trainer.ppo.aux_coef > 0 but the rollout holds no aux targets: pass "
                "aux_targets=findview.task.oracle.rotation_labels(env) (taken before env.step) to storage.insert"
            )
        totals: dict[str, Any] = {}
        num_batches = 0
        warmup = self.progress_update < cfg.critic_warmup_updates  # only the critic learns
        if cfg.kl_to_init_coef > 0 and self.init_policy is None:
            self.init_policy = self._frozen_copy()
        self.policy.train()
        for _ in range(cfg.ppo_epochs):
            for batch in storage.recurrent_minibatches(advantages, cfg.num_mini_batches, generator):
                terms = self._minibatch_terms(batch)
                grad_norm = self._step(terms, warmup)
                # statistics stay on the device until the update ends (no per-mini-batch sync)
                for name, value in terms.items():
                    if name != "loss":
                        totals[name] = totals.get(name, 0.0) + value.detach()
                totals["grad_norm"] = totals.get("grad_norm", 0.0) + grad_norm.detach()
                num_batches += 1

        names = list(totals)
        values = torch.stack([torch.as_tensor(totals[n]).float().reshape(()) for n in names]).tolist() if names else []
        stats = {name: value / num_batches for name, value in zip(names, values)}
        stats["lr"] = self.lr
        stats["clip"] = self.clip
        stats["critic_warmup"] = float(warmup)
        return stats

    def _minibatch_terms(self, batch: Any) -> dict[str, torch.Tensor]:
        """The loss of one mini-batch (``loss``, to minimise) and its reported terms (:func:`ppo_loss`'s, plus
        ``kl_to_init`` and ``aux_loss, aux_rotation_loss, aux_overlap_accuracy`` when those are on)."""
        cfg = self.cfg
        aux_terms: dict[str, torch.Tensor] | None = None
        kl_init: torch.Tensor | None = None
        if self.aux_head is None and self.init_policy is None:
            log_probs, values, entropy = self.policy.evaluate_actions(batch.obs, batch.hidden0, batch.masks, batch.actions)
        else:
            dist, values, _, features = self.policy.forward_features(batch.obs, batch.hidden0, batch.masks)
            log_probs, entropy = dist.log_prob(batch.actions), dist.entropy()
            if self.aux_head is not None:
                assert batch.aux_targets is not None
                aux_terms = aux_loss(self.aux_head(features), batch.aux_targets)
            if self.init_policy is not None:
                with torch.no_grad():
                    init_dist = self.init_policy.forward_features(batch.obs, batch.hidden0, batch.masks)[0]
                kl_init = (init_dist.probs * (init_dist.logits - dist.logits)).sum(dim=-1).mean()
        terms = ppo_loss(
            log_probs, batch.old_log_probs, batch.advantages, values, batch.old_values, batch.returns, entropy,
            clip=self.clip, value_coef=cfg.value_coef, entropy_coef=cfg.entropy_coef,
            clipped_value_loss=cfg.clipped_value_loss,
        )
        if aux_terms is not None:
            terms["loss"] = terms["loss"] + cfg.aux_coef * aux_terms["loss"]
            terms.update({f"aux_{name}": aux_terms[name] for name in ("loss", "rotation_loss", "overlap_accuracy")})
        if kl_init is not None:
            terms["loss"] = terms["loss"] + cfg.kl_to_init_coef * kl_init
            terms["kl_to_init"] = kl_init
        return terms

    def _step(self, terms: dict[str, torch.Tensor], warmup: bool) -> torch.Tensor:
        """Backward, average the gradients over the ranks, clip and step; returns the pre-clipping gradient norm.
        Raises ``FloatingPointError`` (before the step) if the loss or the gradient norm is not finite."""
        self.optimizer.zero_grad(set_to_none=True)
        terms["loss"].backward()
        distributed.allreduce_gradients(self.params)  # average over ranks, before clipping
        if warmup:
            for p in self.frozen_in_warmup:
                p.grad = None  # Adam skips parameters without a gradient
        grad_norm = nn.utils.clip_grad_norm_(self.params, self.cfg.max_grad_norm)
        # one host sync per mini-batch, before the weights change. Distributed: a non-finite local
        # loss shows as a non-finite averaged gradient norm on every rank, so all ranks fail together
        checked = [grad_norm] if distributed.is_active() else [grad_norm, *(v.detach() for v in terms.values())]
        if not bool(torch.isfinite(torch.stack([v.float().reshape(()) for v in checked])).all()):
            if not distributed.is_active():
                _check_finite(terms)
            raise FloatingPointError(f"non-finite gradient norm: {grad_norm.item()}")
        self.optimizer.step()
        return grad_norm

    # ---------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Optimizer state + current lr / clip (+ the aux head's weights when on; the policy weights are
        saved separately)."""
        state: dict[str, Any] = {"optimizer": self.optimizer.state_dict(), "lr": self.lr, "clip": self.clip}
        if self.aux_head is not None:
            state["aux_head"] = self.aux_head.state_dict()
        if self.init_policy is not None:
            state["init_policy"] = self.init_policy.state_dict()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        if (self.aux_head is None) != (state.get("aux_head") is None):
            raise ValueError(
                "saved PPO state and this run disagree on the auxiliary loss (trainer.ppo.aux_coef > 0 in one only)"
            )
        if self.aux_head is not None:
            self.aux_head.load_state_dict(state["aux_head"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.lr, self.clip = state["lr"], state["clip"]
        if self.cfg.kl_to_init_coef > 0 and state.get("init_policy") is not None:
            self.init_policy = self._frozen_copy(state["init_policy"])  # the policy the run started from
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr
