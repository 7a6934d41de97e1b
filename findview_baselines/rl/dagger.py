"""Imitation of the oracle with DAgger (dataset aggregation) for the recurrent policies of ``policy.py``.

The simulator knows the shortest-path action at every state, so every observation the learner visits can
be labelled for free (``findview.task.oracle``; the privileged rotations are never shown to the policy).
One update of :class:`DAggerTrainer`::

    beta = beta_start -> beta_end, linearly over beta_decay_updates updates
    for rollout_steps steps (N environments):
        oracle = oracle_actions_for(env, order, search_prior)        # before env.step: the expert's action
        label  = the set of actions the expert accepts: {oracle} (labels=action) or every shortest-path
                 action (labels=set, optimal_action_mask_for)
        learner action from policy.act (argmax unless sample_actions)
        execute the oracle's action with probability beta (per env, per step), else the learner's
    cut the T x N rollout into chunks of seq_len steps (GRU state at each chunk start, episode masks)
    push the chunks into a FIFO buffer of buffer_size steps (the oldest chunks drop out)
    ceil(epochs * new_chunks / batch_sequences) Adam steps, each on batch_sequences chunks drawn uniformly
        (without replacement) from the buffer: weighted negative log-likelihood of the label set,
        -log sum_{a in set} pi(a | obs) (the cross-entropy for a one-action set), + aux_coef * auxiliary
        rotation loss; gradient norm clipped at max_grad_norm

Labels (``labels``): ``"action"`` (default) imitates the oracle's one action (its axis order); ``"set"``
accepts any action on a shortest path (both axes while both are off), so the learner may fix whichever
axis it sees best first instead of having to tell which remaining distance the order picks.

Search prior (``search_prior``): ``"oracle"`` labels every state with the true shortest path, also where the view
and the target share nothing, so a learner must guess the direction there; ``"pan"`` (default) replaces
the labels of no-overlap states by "pan right until the views overlap" (``findview.task.oracle.pan_actions``),
which a learner can follow from images alone (it only has to tell whether the views overlap);
``"sweep"`` first matches the pitch, then pans right (``sweep_actions``); a learner cannot read the
target's pitch from a view that shares nothing with it and a greedy one ends in ``UP``/``DOWN`` two-cycles.

Recurrent training: a chunk starts from the GRU state the learner had at that step during the rollout
(stale once the weights move on, as in recurrent PPO), and ``masks == 0`` zero the state where an episode
starts inside a chunk.

A stop request during the rollout (``train_update(should_stop)``) abandons the update with
``UpdateAbandoned`` before anything reaches the buffer, and :meth:`DAggerTrainer.state_dict` then describes
the state before that update, as for ``PPOTrainer``.

Resume: :meth:`DAggerTrainer.state_dict` holds the policy, the optimizer, the environment (running
episodes), the current observation / GRU state, every RNG and (``save_buffer``) the buffer, so N updates
and N/2 + resume + N/2 give the same weights on CPU. The buffer takes ``2 * buffer_size * 3 * H * W``
bytes of uint8 images (about 400 MB for 16384 steps of 64x64 views) in memory and in ``latest.pth``; with
``save_buffer=false`` the checkpoint stays small and a resumed run refills the buffer (not exact).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Any, Callable, Mapping

import torch
from torch import nn

from findview.task import NUM_ACTIONS
from findview.task.oracle import (
    ORDERS,
    SEARCH_PRIORS,
    optimal_action_mask_for,
    oracle_actions_for,
    overlap_mask,
    rotation_labels,
)
from findview_baselines.agents.revisit import make_revisit_penalty
from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import capture_rng_state, restore_rng_state
from findview_baselines.rl.policy import AuxHead, Policy, aux_loss, check_signature
from findview_baselines.rl.ppo_trainer import UpdateAbandoned, no_distribution_validation
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import AUX_SIZE

__all__ = ["DAggerConfig", "DAggerTrainer", "SequenceBuffer", "STAT_KEYS", "TIMING_KEYS", "beta_at", "set_nll"]

TIMING_KEYS = ("env_step", "policy_forward", "rollout_other", "update")
# scalar entries of train_update()'s stats (besides update / env_steps / level / episodes)
STAT_KEYS = (
    "policy_loss", "accuracy", "stop_accuracy", "entropy", "grad_norm", "lr", "beta", "buffer_steps",
    "oracle_share", "rollout_agreement",
)
AUX_STAT_KEYS = ("aux_loss", "aux_rotation_loss", "aux_overlap_accuracy")
STOP = NUM_ACTIONS - 1
LABEL_MODES = ("action", "set")


@dataclass
class DAggerConfig:
    """DAgger hyper-parameters (``trainer=dagger``). Units: steps are environment steps of one env."""

    lr: float = 1e-3
    """Adam learning rate."""
    adam_eps: float = 1e-5
    """Adam epsilon."""
    max_grad_norm: float = 1.0
    """Gradient norm clip (over the policy and the aux head)."""
    linear_decay: bool = False
    """Decay the learning rate linearly to 0 over the run's ``total_updates``."""
    rollout_steps: int = 32
    """Steps per environment per update (a multiple of ``seq_len``)."""
    seq_len: int = 16
    """Length (steps) of the sequences the GRU trains on; chunks of the rollout go into the buffer."""
    buffer_size: int = 16384
    """Buffer capacity in labelled steps (``buffer_size // seq_len`` chunks, FIFO)."""
    epochs: float = 4.0
    """Gradient steps per update = ceil(epochs * new chunks / batch_sequences): on average each new chunk is
    used ``epochs`` times while it is the newest data (older chunks keep being sampled)."""
    batch_sequences: int = 16
    """Chunks per mini-batch (``batch_sequences * seq_len`` labelled steps)."""
    beta_start: float = 1.0
    """Probability (per env, per step) of executing the oracle's label instead of the learner's action at
    update 0."""
    beta_end: float = 0.0
    """That probability from update ``beta_decay_updates`` on."""
    beta_decay_updates: int = 60
    """Updates over which beta falls linearly from ``beta_start`` to ``beta_end`` (0: ``beta_end`` at once)."""
    stop_weight: float = 1.0
    """Cross-entropy class weight of ``stop`` (the four moves weigh 1): above 1 penalises missed stops more."""
    search_weight: float = 1.0
    """Loss weight of the steps where view and target do not overlap (the search prior's labels; 1 = as
    any step). Hard episodes are long, so at the last curriculum level most labelled steps are "pan right":
    below 1 keeps them from drowning the few steps that find and stop on the target."""
    search_prior: str = "pan"
    """Labels where view and target do not overlap: ``pan`` (pan right until they do), ``sweep`` (match
    pitch, then pan right) or ``oracle`` (the true shortest path, which a learner cannot see)."""
    order: str = "pitch_first"
    """Axis order of the oracle's executed actions (and of the labels with ``labels=action``):
    ``pitch_first``, ``yaw_first`` or ``larger_first``."""
    labels: str = "action"
    """``action``: the oracle's one action (cross-entropy); ``set``: any shortest-path action is right
    (likelihood of the set)."""
    sample_actions: bool = False
    """The learner executes sampled actions (true) or its argmax, as at evaluation (false)."""
    aux_coef: float = 0.0
    """Weight of the auxiliary rotation / overlap loss (0 = off)."""
    save_buffer: bool = True
    """Store the buffer in ``state_dict`` (exact resume, large checkpoints); false: a resume refills it."""

    def __post_init__(self) -> None:
        positive = ("lr", "rollout_steps", "seq_len", "buffer_size", "batch_sequences", "epochs")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"dagger.{name} must be positive, got {getattr(self, name)!r}")
        if self.rollout_steps % self.seq_len:
            raise ValueError(
                f"dagger.rollout_steps ({self.rollout_steps}) must be a multiple of dagger.seq_len ({self.seq_len})"
            )
        if self.buffer_size < self.seq_len:
            raise ValueError(
                f"dagger.buffer_size ({self.buffer_size}) must hold one sequence of {self.seq_len} steps"
            )
        for name in ("beta_start", "beta_end"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"dagger.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.beta_decay_updates < 0:
            raise ValueError(f"dagger.beta_decay_updates must be >= 0, got {self.beta_decay_updates}")
        if self.search_weight <= 0:
            raise ValueError(f"dagger.search_weight must be positive, got {self.search_weight!r}")
        if self.stop_weight <= 0 or self.aux_coef < 0 or self.max_grad_norm <= 0:
            raise ValueError(
                f"dagger: need stop_weight > 0, aux_coef >= 0, max_grad_norm > 0; got {self.stop_weight}, "
                f"{self.aux_coef}, {self.max_grad_norm}"
            )
        if self.search_prior not in SEARCH_PRIORS:
            raise ValueError(f"dagger.search_prior must be one of {SEARCH_PRIORS}, got {self.search_prior!r}")
        if self.labels not in LABEL_MODES:
            raise ValueError(f"dagger.labels must be one of {LABEL_MODES}, got {self.labels!r}")
        if self.order not in ORDERS:
            raise ValueError(f"dagger.order must be one of {ORDERS}, got {self.order!r}")

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> "DAggerConfig":
        """Pick the known keys of a (Hydra / dict) config; other keys are ignored."""
        known = {f.name for f in fields(cls)}
        return cls(**{k: cfg[k] for k in known if k in cfg})


def set_nll(
    logits: torch.Tensor,
    accepted: torch.Tensor,
    class_weights: torch.Tensor | None = None,
    row_weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean negative log-likelihood of the accepted actions: ``-log sum_{a in set} softmax(logits)_a``.

    Args:
        logits: (B, 5) action logits.
        accepted: (B, 5) bool, at least one true per row (a one-hot row gives the plain cross-entropy).
        class_weights: optional (5,) weights; a row weighs the largest weight among its accepted actions
            (so ``stop_weight`` applies to rows whose answer is ``stop``); the mean is weighted, as in
            ``torch.nn.functional.cross_entropy``.
        row_weights: optional (B,) weights multiplying each row's weight (e.g. ``search_weight`` on the
            no-overlap rows).
    """
    log_probs = torch.log_softmax(logits, dim=-1)
    nll = -torch.logsumexp(log_probs.masked_fill(~accepted, float("-inf")), dim=-1)
    if class_weights is None and row_weights is None:
        return nll.mean()
    w = (accepted.float() * class_weights).amax(dim=-1) if class_weights is not None else torch.ones_like(nll)
    if row_weights is not None:
        w = w * row_weights
    return (w * nll).sum() / w.sum()


def beta_at(cfg: DAggerConfig, update: int) -> float:
    """Oracle-execution probability at ``update`` (0-based): linear from ``beta_start`` to ``beta_end``."""
    if cfg.beta_decay_updates <= 0:
        return cfg.beta_end
    frac = min(1.0, update / cfg.beta_decay_updates)
    return cfg.beta_start + (cfg.beta_end - cfg.beta_start) * frac


# --------------------------------------------------------------------------------------------------
# Buffer
# --------------------------------------------------------------------------------------------------


class SequenceBuffer:
    """FIFO ring of ``capacity`` labelled sequences of ``seq_len`` steps on ``device``.

    Per chunk: view, target (L, 3, H, W) uint8; hidden0 (hidden,) the GRU state entering its first step;
    masks (L,) (0 where an episode starts); labels (L, 5) bool (the accepted actions); aux (L, 3) float
    (when ``with_aux``).
    """

    def __init__(
        self,
        capacity: int,
        seq_len: int,
        height: int,
        width: int,
        hidden_size: int,
        device: torch.device | str = "cpu",
        with_aux: bool = False,
    ) -> None:
        self.capacity, self.seq_len = int(capacity), int(seq_len)
        self.device = torch.device(device)
        c, L, kw = self.capacity, self.seq_len, {"device": self.device}
        self.view = torch.empty(c, L, 3, height, width, dtype=torch.uint8, **kw)
        self.target = torch.empty(c, L, 3, height, width, dtype=torch.uint8, **kw)
        self.hidden0 = torch.empty(c, hidden_size, **kw)
        self.masks = torch.empty(c, L, **kw)
        self.labels = torch.empty(c, L, NUM_ACTIONS, dtype=torch.bool, **kw)
        self.weights = torch.ones(c, L, **kw)
        self.aux = torch.empty(c, L, AUX_SIZE, **kw) if with_aux else None
        self.pos = 0  # next slot to write
        self.size = 0  # filled slots

    def __len__(self) -> int:
        return self.size

    def add(
        self,
        view: torch.Tensor,
        target: torch.Tensor,
        hidden0: torch.Tensor,
        masks: torch.Tensor,
        labels: torch.Tensor,
        aux: torch.Tensor | None = None,
        weights: torch.Tensor | None = None,
    ) -> None:
        """Append ``n`` chunks given time-major: view / target (L, n, 3, H, W), hidden0 (n, hidden), masks
        (L, n), labels (L, n, 5) bool, aux (L, n, 3), weights (L, n) loss weights (default 1). The oldest
        chunks are overwritten when full."""
        n = hidden0.shape[0]
        if n > self.capacity:  # keep the newest
            keep = slice(n - self.capacity, n)
            view, target, masks, labels = view[:, keep], target[:, keep], masks[:, keep], labels[:, keep]
            hidden0 = hidden0[keep]
            aux = None if aux is None else aux[:, keep]
            weights = None if weights is None else weights[:, keep]
            n = self.capacity
        slots = (torch.arange(n) + self.pos) % self.capacity
        slots = slots.to(self.device)
        self.view[slots] = view.transpose(0, 1).to(self.device)
        self.target[slots] = target.transpose(0, 1).to(self.device)
        self.hidden0[slots] = hidden0.to(self.device)
        self.masks[slots] = masks.transpose(0, 1).to(self.device, torch.float32)
        self.labels[slots] = labels.transpose(0, 1).to(self.device, torch.bool)
        self.weights[slots] = 1.0 if weights is None else weights.transpose(0, 1).to(self.device, torch.float32)
        if self.aux is not None:
            if aux is None:
                raise ValueError("this buffer stores aux targets; add() needs aux")
            self.aux[slots] = aux.transpose(0, 1).to(self.device, torch.float32)
        self.pos = (self.pos + n) % self.capacity
        self.size = min(self.capacity, self.size + n)

    def sample(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """``min(count, size)`` distinct chunk indices, uniform (CPU ``generator``)."""
        if self.size == 0:
            raise ValueError("the DAgger buffer is empty")
        return torch.randperm(self.size, generator=generator)[: min(count, self.size)].to(self.device)

    def batch(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """The chunks ``index`` (b,), time-major flattened like a rollout: obs (L*b, 3, H, W), masks (L*b,),
        labels (L*b, 5), weights (L*b,), aux (L*b, 3) or absent, hidden0 (b, hidden)."""

        def tm(x: torch.Tensor) -> torch.Tensor:
            return x[index].transpose(0, 1).flatten(0, 1)

        out = {
            "view": tm(self.view),
            "target": tm(self.target),
            "masks": tm(self.masks),
            "labels": tm(self.labels),
            "weights": tm(self.weights),
            "hidden0": self.hidden0[index],
        }
        if self.aux is not None:
            out["aux"] = tm(self.aux)
        return out

    def state_dict(self) -> dict[str, Any]:
        """The filled part (CPU tensors) and the write position."""
        n = self.size
        state: dict[str, Any] = {
            "pos": self.pos,
            "size": n,
            "view": self.view[:n].cpu().clone(),
            "target": self.target[:n].cpu().clone(),
            "hidden0": self.hidden0[:n].cpu().clone(),
            "masks": self.masks[:n].cpu().clone(),
            "labels": self.labels[:n].cpu().clone(),
            "weights": self.weights[:n].cpu().clone(),
        }
        if self.aux is not None:
            state["aux"] = self.aux[:n].cpu().clone()
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        n = int(state["size"])
        if n > self.capacity:
            raise ValueError(
                f"saved DAgger buffer holds {n} chunks, this one only {self.capacity} (dagger.buffer_size)"
            )
        if tuple(state["view"].shape[1:]) != tuple(self.view.shape[1:]):
            raise ValueError(
                f"saved DAgger buffer chunks are {tuple(state['view'].shape[1:])}, "
                f"expected {tuple(self.view.shape[1:])}"
            )
        for name in ("view", "target", "hidden0", "masks", "labels"):
            getattr(self, name)[:n] = state[name].to(self.device)
        self.weights[:n] = state["weights"].to(self.device) if state.get("weights") is not None else 1.0
        if self.aux is not None:
            if state.get("aux") is None:
                raise ValueError("saved DAgger buffer has no aux targets but dagger.aux_coef > 0")
            self.aux[:n] = state["aux"].to(self.device)
        self.size, self.pos = n, int(state["pos"]) % self.capacity


# --------------------------------------------------------------------------------------------------
# Trainer
# --------------------------------------------------------------------------------------------------


def _masks(env: Any, device: torch.device) -> torch.Tensor:
    """(N,) float: 0 where the env's current observation starts a new episode."""
    return (~env.new_episode).to(device=device, dtype=torch.float32)


def _never() -> bool:
    return False


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class DAggerTrainer:
    """DAgger on a batched FindView environment, with the public interface of ``PPOTrainer``.

    Args:
        env: a batched, auto-resetting :class:`~findview.task.FindViewEnv` (its privileged ``pitch, yaw,
            target_pitch, target_yaw`` and ``sim.fov`` give the labels).
        policy: the :class:`Policy` (already on its device).
        cfg: :class:`DAggerConfig`.
        total_updates: updates of the whole run (lr decay, scheduler).
        scheduler, set_level: optional difficulty curriculum, as for ``PPOTrainer``.
        seed: seeds the trainer's own generators (beta mixing, buffer sampling); learner action sampling
            (``sample_actions``) uses torch's global RNG.

    :meth:`start` for a fresh run or :meth:`load_state_dict` to resume; then :meth:`train_update` repeatedly.
    """

    def __init__(
        self,
        env: Any,
        policy: Policy,
        cfg: DAggerConfig,
        total_updates: int,
        scheduler: DifficultyScheduler | None = None,
        set_level: Callable[[int], None] | None = None,
        seed: int = 0,
        revisit_penalty: float = 0.0,
        revisit_row_stride: int = 0,
    ) -> None:
        self.env = env
        self.policy = policy
        self.cfg = cfg
        self.total_updates = int(total_updates)
        self.scheduler = scheduler
        self.set_level = set_level
        self.device = next(policy.parameters()).device
        self.aux_head: AuxHead | None = AuxHead(policy.feature_size).to(self.device) if cfg.aux_coef > 0 else None
        self.params = list(policy.parameters()) + (list(self.aux_head.parameters()) if self.aux_head else [])
        self.optimizer = torch.optim.Adam(self.params, lr=cfg.lr, eps=cfg.adam_eps)
        self.lr = cfg.lr
        n, dev = env.num_envs, self.device
        self.buffer = SequenceBuffer(
            max(1, cfg.buffer_size // cfg.seq_len), cfg.seq_len, policy.height, policy.width,
            policy.hidden_size, dev, with_aux=self.aux_head is not None,
        )
        weights = torch.ones(NUM_ACTIONS, device=dev)
        weights[STOP] = cfg.stop_weight
        self.class_weights = weights
        self.mix_generator = torch.Generator().manual_seed(seed)
        self.sample_generator = torch.Generator().manual_seed(seed + 1)
        # current observation (a copy: the env's buffers change in place), GRU state and masks
        self.view = torch.zeros(n, 3, policy.height, policy.width, dtype=torch.uint8, device=dev)
        self.target = torch.zeros_like(self.view)
        self.hidden = policy.initial_hidden(n, dev)
        self.masks = torch.zeros(n, device=dev)
        self.episode_returns = torch.zeros(n, device=dev)
        self.update = 0
        self.env_steps = 0
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        self._before_update: dict[str, Any] | None = None  # resume parts while a rollout runs
        # the learner acts in rollouts as the evaluated agent will (agent.revisit_penalty: its search memory)
        self.revisits = make_revisit_penalty(n, dev, revisit_penalty, revisit_row_stride)
        self._all_slots = torch.arange(n, device=dev)

    # ---------------------------------------------------------------------------------------------

    def _set_obs(self, obs: Mapping[str, torch.Tensor]) -> None:
        self.view.copy_(obs["view"])
        self.target.copy_(obs["target"])

    def start(self) -> None:
        """Fresh run: set the difficulty level for ``self.update`` and reset the environments."""
        if self.scheduler is not None:
            self.scheduler.step(self.update)
            if self.set_level is not None:
                self.set_level(self.scheduler.current_level)
        self._set_obs(self.env.reset())
        self.hidden.zero_()
        self.masks.copy_(_masks(self.env, self.device))
        self.episode_returns.zero_()

    @torch.no_grad()
    def collect_rollout(
        self, beta: float, should_stop: Callable[[], bool] = _never
    ) -> tuple[list[dict[str, Any]], dict[str, float]]:
        """Run ``rollout_steps`` mixed steps and push the labelled chunks into the buffer.

        Returns the finished episodes' records (with ``"return"``) and rollout stats (``oracle_share``:
        share of executed oracle actions; ``rollout_agreement``: share of steps where the learner's action
        was in the label set). Raises ``UpdateAbandoned`` (buffer untouched) when ``should_stop()`` turns
        true before a step.
        """
        cfg, env, dev = self.cfg, self.env, self.device
        T, n = cfg.rollout_steps, env.num_envs
        views = torch.empty(T, *self.view.shape, dtype=torch.uint8, device=dev)
        targets = torch.empty_like(views)
        hiddens = torch.empty(T // cfg.seq_len, *self.hidden.shape, device=dev)
        masks = torch.empty(T, n, device=dev)
        labels = torch.empty(T, n, NUM_ACTIONS, dtype=torch.bool, device=dev)
        weights = torch.ones(T, n, device=dev)
        aux = torch.empty(T, n, AUX_SIZE, device=dev) if self.aux_head is not None else None
        records: list[dict[str, Any]] = []
        agree = torch.zeros((), device=dev)
        executed_oracle = 0
        self.policy.eval()
        t_forward = t_env = 0.0
        start = time.perf_counter()
        for t in range(T):
            if should_stop():
                raise UpdateAbandoned(f"update {self.update + 1} abandoned during its rollout")
            views[t].copy_(self.view)
            targets[t].copy_(self.target)
            masks[t].copy_(self.masks)
            if t % cfg.seq_len == 0:
                hiddens[t // cfg.seq_len].copy_(self.hidden * self.masks[:, None])
            oracle = oracle_actions_for(env, cfg.order, cfg.search_prior).to(dev)
            if cfg.labels == "set":
                label = optimal_action_mask_for(env, cfg.search_prior).to(dev)
            else:
                label = nn.functional.one_hot(oracle, NUM_ACTIONS).bool()
            labels[t].copy_(label)
            if cfg.search_weight != 1.0:
                overlap = overlap_mask(env.pitch, env.yaw, env.target_pitch, env.target_yaw, float(env.sim.fov))
                weights[t].masked_fill_(~overlap.to(dev), cfg.search_weight)
            if aux is not None:
                aux[t].copy_(rotation_labels(env).to(dev))
            t0 = time.perf_counter()
            obs = {"view": self.view, "target": self.target}
            if self.revisits is None:
                learner, _, _, new_hidden = self.policy.act(
                    obs, self.hidden, self.masks, deterministic=not cfg.sample_actions
                )
            else:
                learner, new_hidden = self._act_with_revisits(obs)
            t1 = time.perf_counter()
            use_oracle = torch.rand(n, generator=self.mix_generator) < beta
            executed_oracle += int(use_oracle.sum())
            agree += label.gather(1, learner[:, None]).sum()
            actions = torch.where(use_oracle.to(dev), oracle, learner)
            if self.revisits is not None:
                self.revisits.moved(self._all_slots, actions)  # what was executed, oracle or learner
            next_obs, rewards, done, infos = env.step(actions)
            t2 = time.perf_counter()
            t_forward += t1 - t0
            t_env += t2 - t1
            self._set_obs(next_obs)
            self.hidden = new_hidden
            self.masks = _masks(env, dev)
            self.episode_returns += rewards.to(dev, torch.float32)
            finished = [i for i, info in enumerate(infos) if info is not None]
            if finished:
                returns = self.episode_returns[finished].tolist()
                records += [{**infos[i], "return": r} for i, r in zip(finished, returns)]
            self.episode_returns.masked_fill_(done.to(dev), 0.0)

        L = cfg.seq_len
        for k in range(T // L):
            s = slice(k * L, (k + 1) * L)
            self.buffer.add(
                views[s], targets[s], hiddens[k], masks[s], labels[s], None if aux is None else aux[s], weights[s]
            )
        self.env_steps += distributed.global_steps(T * n)  # all ranks under torchrun
        total = time.perf_counter() - start
        self.timings["policy_forward"] += t_forward
        self.timings["env_step"] += t_env
        self.timings["rollout_other"] += total - t_forward - t_env
        stats = {"oracle_share": executed_oracle / (T * n), "rollout_agreement": float(agree) / (T * n)}
        return records, stats

    def _act_with_revisits(self, obs: Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """The learner's actions under its search memory (as ``PPOAgent`` acts at evaluation) and new GRU state."""
        assert self.revisits is not None
        starts = torch.nonzero(self.masks == 0).flatten()
        if len(starts):
            self.revisits.reset(starts)
        dist, _, new_hidden = self.policy(obs, self.hidden, self.masks)
        logits = self.revisits.adjust(self._all_slots, obs["view"], dist.logits)
        if self.cfg.sample_actions:
            return torch.distributions.Categorical(logits=logits).sample(), new_hidden
        return logits.argmax(dim=-1), new_hidden

    def _train(self, new_chunks: int) -> dict[str, float]:
        """Gradient steps on the buffer; mean stats over them."""
        cfg = self.cfg
        steps = max(1, math.ceil(cfg.epochs * new_chunks / cfg.batch_sequences))
        totals: dict[str, float] = {}
        self.policy.train()
        for _ in range(steps):
            b = self.buffer.batch(self.buffer.sample(cfg.batch_sequences, self.sample_generator))
            obs = {"view": b["view"], "target": b["target"]}
            dist, _, _, features = self.policy.forward_features(obs, b["hidden0"], b["masks"])
            logits = dist.logits
            labels = b["labels"]
            ce = set_nll(logits, labels, self.class_weights, b["weights"])
            loss = ce
            terms = {"policy_loss": ce}
            if self.aux_head is not None:
                aux_terms = aux_loss(self.aux_head(features), b["aux"])
                loss = loss + cfg.aux_coef * aux_terms["loss"]
                terms.update(
                    aux_loss=aux_terms["loss"], aux_rotation_loss=aux_terms["rotation_loss"],
                    aux_overlap_accuracy=aux_terms["overlap_accuracy"],
                )
            if not bool(torch.isfinite(loss)) and not distributed.is_active():  # distributed: caught below
                raise FloatingPointError(f"non-finite DAgger loss: {loss.item()}")
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            distributed.allreduce_gradients(self.params)  # under torchrun: average over ranks, before clipping
            grad_norm = nn.utils.clip_grad_norm_(self.params, cfg.max_grad_norm)
            if not torch.isfinite(grad_norm):
                raise FloatingPointError(f"non-finite gradient norm: {grad_norm.item()}")
            self.optimizer.step()
            with torch.no_grad():
                pred = logits.argmax(dim=-1)
                is_stop = labels[:, STOP]
                terms["accuracy"] = labels.gather(1, pred[:, None]).float().mean()
                terms["stop_accuracy"] = (
                    (pred[is_stop] == STOP).float().mean() if bool(is_stop.any()) else torch.tensor(float("nan"))
                )
                terms["entropy"] = dist.entropy().mean()
                terms["grad_norm"] = grad_norm
            for key, value in terms.items():
                v = float(value.detach()) if isinstance(value, torch.Tensor) else float(value)
                if key == "stop_accuracy" and math.isnan(v):
                    continue
                totals[key] = totals.get(key, 0.0) + v
                totals[f"_n_{key}"] = totals.get(f"_n_{key}", 0.0) + 1.0
        return {k: v / totals[f"_n_{k}"] for k, v in totals.items() if not k.startswith("_n_")}

    def train_update(self, should_stop: Callable[[], bool] = _never) -> dict[str, Any]:
        """One mixed rollout + training on the buffer; returns the stats (:data:`STAT_KEYS`, plus
        :data:`AUX_STAT_KEYS` with aux on), ``update``, ``env_steps``, ``level`` and ``episodes``.

        ``should_stop`` is polled before every rollout step (see ``PPOTrainer.train_update``). Raises
        ``FloatingPointError`` when the loss, the gradient or the updated weights are not finite.
        """
        self._before_update = self._resume_parts()
        if self.scheduler is not None and self.scheduler.step(self.update) and self.set_level is not None:
            self.set_level(self.scheduler.current_level)
        cfg = self.cfg
        if cfg.linear_decay and self.total_updates > 0:
            self.lr = cfg.lr * max(0.0, 1.0 - self.update / self.total_updates)
        else:
            self.lr = cfg.lr
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr
        beta = beta_at(cfg, self.update)

        with no_distribution_validation():
            records, rollout_stats = self.collect_rollout(beta, should_stop)
        self._before_update = None
        t0 = time.perf_counter()
        try:
            with no_distribution_validation():
                stats: dict[str, Any] = self._train((cfg.rollout_steps // cfg.seq_len) * self.env.num_envs)
            self._check_weights()
        finally:
            _sync(self.device)
            self.timings["update"] += time.perf_counter() - t0
        self.update += 1
        stats.setdefault("stop_accuracy", float("nan"))
        stats.update(rollout_stats)
        stats["lr"] = self.lr
        stats["beta"] = beta
        stats["buffer_steps"] = len(self.buffer) * cfg.seq_len
        stats["update"] = self.update
        stats["env_steps"] = self.env_steps
        stats["level"] = self.scheduler.current_level if self.scheduler is not None else None
        stats["episodes"] = records
        return stats

    def _check_weights(self) -> None:
        finite = torch.stack([torch.isfinite(p).all() for p in self.params]).all()
        if not bool(finite):
            bad = [name for name, p in self.policy.named_parameters() if not torch.isfinite(p).all()]
            raise FloatingPointError(f"non-finite weights after the optimizer step: {', '.join(bad[:5]) or 'aux head'}")

    def pop_timings(self) -> dict[str, float]:
        """Seconds per phase since the last call (keys :data:`TIMING_KEYS`), then reset them."""
        out = dict(self.timings)
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        return out

    # ---------------------------------------------------------------------------------------------
    # Resume state
    # ---------------------------------------------------------------------------------------------

    def _resume_parts(self) -> dict[str, Any]:
        """The parts of the resume state that a rollout changes (environment, current step, RNGs)."""
        return {
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else None,
            "env_steps": self.env_steps,
            "env": self.env.state_dict() if hasattr(self.env, "state_dict") else None,
            "current": {
                "view": self.view.cpu().clone(),
                "target": self.target.cpu().clone(),
                "hidden": self.hidden.cpu().clone(),
                "masks": self.masks.cpu().clone(),
            },
            "episode_returns": self.episode_returns.cpu().clone(),
            "mix_rng": self.mix_generator.get_state(),
            "rng": capture_rng_state(),
            "revisits": self.revisits.state_dict() if self.revisits is not None else None,
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (plain values + tensors: ``weights_only=True`` loads it).

        After an abandoned update these describe the state before it (the weights, the optimizer and the
        buffer are untouched by an abandoned rollout)."""
        parts = self._before_update if self._before_update is not None else self._resume_parts()
        return {
            "kind": "dagger",
            "signature": self.policy.model_signature(),
            "policy": self.policy.state_dict(),
            "aux_head": self.aux_head.state_dict() if self.aux_head is not None else None,
            "optimizer": self.optimizer.state_dict(),
            "lr": self.lr,
            "update": self.update,
            "sample_rng": self.sample_generator.get_state(),
            "buffer": self.buffer.state_dict() if self.cfg.save_buffer else None,
            **parts,
        }

    def load_state_dict(self, state: Mapping[str, Any], restore_rng: bool = True) -> None:
        """Resume from :meth:`state_dict` (see ``PPOTrainer.load_state_dict``). Raises ``ValueError`` on a
        model mismatch or a state saved by another trainer."""
        if state.get("kind") != "dagger":
            raise ValueError("this trainer state was not saved by the DAgger trainer (trainer=dagger)")
        check_signature(state["signature"], self.policy.model_signature())
        if (self.aux_head is None) != (state.get("aux_head") is None):
            raise ValueError(
                "saved DAgger state and this run disagree on the auxiliary loss (aux_coef > 0 in one only)"
            )
        self.policy.load_state_dict(state["policy"])
        if self.aux_head is not None:
            self.aux_head.load_state_dict(state["aux_head"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.lr = float(state["lr"])
        if self.scheduler is not None and state.get("scheduler") is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        self.update = int(state["update"])
        self.env_steps = int(state["env_steps"])
        env_state = state.get("env")
        if env_state is not None and hasattr(self.env, "load_state_dict"):
            self.env.load_state_dict(env_state)
        cur = state.get("current")
        if cur is not None:
            self.view.copy_(cur["view"])
            self.target.copy_(cur["target"])
            self.hidden = cur["hidden"].to(self.device).clone()
            self.masks = cur["masks"].to(self.device).clone()
        if state.get("episode_returns") is not None:
            self.episode_returns.copy_(state["episode_returns"])
        self.mix_generator.set_state(state["mix_rng"])
        self.sample_generator.set_state(state["sample_rng"])
        if self.revisits is not None and state.get("revisits") is not None:
            self.revisits.load_state_dict(state["revisits"])
        if state.get("buffer") is not None:
            self.buffer.load_state_dict(state["buffer"])
        if restore_rng and state.get("rng") is not None:
            restore_rng_state(state["rng"])
