"""The PPO update loop: collect ``rollout_steps`` steps of every environment, then one PPO update.

The environment follows the ``findview.task.FindViewEnv`` contract (docs/ARCHITECTURE.md)::

    obs = env.reset()                                  # {"view", "target"}: (N, 3, H, W) uint8
    obs, reward, done, infos = env.step(actions)       # reward (N,), done (N,) bool, infos[i] record or None
    env.new_episode                                    # (N,) bool: obs[i] starts an episode -> mask 0

:class:`PPOTrainer` is one *algorithm* of the training run loop: a
:class:`~findview_baselines.rl.trainer_base.Trainer` (``kind = "ppo"``), whose interface the run loop drives.

A stop request (a signal) during the rollout abandons the update: :class:`UpdateAbandoned` is raised
and :meth:`PPOTrainer.state_dict` then describes the state *before* that update (environment, rollout
start, RNGs), so a resumed run repeats it exactly and no update is lost or done twice.

Under torchrun (:mod:`findview_baselines.rl.distributed`) every rank runs this loop on its own
environments; the PPO update averages the gradients and the advantage statistics over the ranks, and
``env_steps`` counts the steps of all ranks.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Callable, Iterator, Mapping

import torch
from torch import nn

from findview.runtime import scoped
from findview.task.oracle import rotation_labels
from findview_baselines.rl import distributed
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import RolloutStorage
from findview_baselines.rl.trainer_base import (
    TIMING_KEYS,
    Trainer,
    UpdateAbandoned,
    never,
    no_distribution_validation,
)

# UpdateAbandoned, no_distribution_validation and TIMING_KEYS live in trainer_base; re-exported for old imports
__all__ = ["PPOTrainer", "UpdateAbandoned", "no_distribution_validation", "TIMING_KEYS"]


@contextlib.contextmanager
def _first_steps(storage: RolloutStorage, steps: int) -> Iterator[None]:
    """Let GAE and the PPO update see only the first ``steps`` steps of ``storage`` (a preempted rollout),
    then put the state after them where :meth:`RolloutStorage.after_update` takes the next start from.
    A full rollout (``steps == num_steps``) is left untouched."""
    full = storage.num_steps
    if steps == full:
        yield
        return
    aux_valid = storage.aux_valid.clone()
    storage.num_steps = steps
    storage.aux_valid[steps:] = bool(aux_valid[:steps].all())  # unused rows: aux targets as the used ones
    try:
        yield
    finally:
        storage.num_steps = full
        storage.aux_valid.copy_(aux_valid)
        for name in ("view", "target", "hidden", "masks"):
            getattr(storage, name)[full].copy_(getattr(storage, name)[steps])


# --------------------------------------------------------------------------------------------------
# The update loop
# --------------------------------------------------------------------------------------------------


class PPOTrainer(Trainer):
    """Collects ``rollout_steps`` steps of ``env.num_envs`` environments per update and runs PPO on them.

    Args:
        env: a batched, auto-resetting FindView environment (see module docstring).
        policy: the :class:`Policy` (already on ``device``).
        cfg: PPO hyper-parameters.
        total_updates: number of updates of the whole run (drives lr / clip decay and the scheduler).
        scheduler: optional difficulty scheduler.
        set_level: called with the new level when the scheduler levels up (and at :meth:`start`), e.g.
            ``lambda k: setattr(source, "level", k)``.
        seed: seeds the mini-batch shuffles (action sampling uses torch's global RNG: seed it in the caller).

    Use :meth:`start` for a fresh run, or :meth:`load_state_dict` (which also restores the environment and
    the rollout state when the saved state has them) to resume; then call :meth:`train_update` repeatedly.
    ``timings`` accumulates wall-clock seconds per phase (:data:`TIMING_KEYS`) since the last
    :meth:`pop_timings`.
    """

    kind = "ppo"
    title = "PPO"
    supports_preemption = True
    cfg: PPOConfig

    def __init__(
        self,
        env: Any,
        policy: Policy,
        cfg: PPOConfig,
        total_updates: int,
        scheduler: DifficultyScheduler | None = None,
        set_level: Callable[[int], None] | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__(env, policy, cfg, total_updates, scheduler, set_level)
        self.ppo = PPO(policy, cfg)
        self.storage = RolloutStorage(
            cfg.rollout_steps, env.num_envs, policy.height, policy.width, policy.hidden_size, self.device
        )
        self.shuffle_generator = torch.Generator().manual_seed(seed)
        self.collected = cfg.rollout_steps  # steps of the last rollout (fewer when preempted)

    # ---------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Fresh run: set the difficulty level for ``self.update`` and reset the environments."""
        self._step_level(force=True)
        obs = self.env.reset()
        self.storage.set_initial(obs, self._masks())
        self.episode_returns.zero_()

    def extra_modules(self) -> list[nn.Module]:
        """The PPO auxiliary rotation head when ``aux_coef > 0``, else nothing."""
        return [self.ppo.aux_head] if self.ppo.aux_head is not None else []

    @torch.no_grad()
    def collect_rollout(self, should_stop: Callable[[], bool] = never) -> list[dict[str, Any]]:
        """Run ``rollout_steps`` steps, filling the storage; returns the records of finished episodes
        (each with an extra ``"return"``: the undiscounted reward sum).

        Raises :class:`UpdateAbandoned` when ``should_stop()`` turns true before a step. With
        :attr:`preemption` the rollout may end early (:attr:`collected` steps) and ``env_steps`` is left to
        :meth:`train_update`."""
        records: list[dict[str, Any]] = []
        self.policy.eval()
        t_forward = t_env = 0.0
        start = time.perf_counter()
        preemption, T = self.preemption, self.cfg.rollout_steps
        min_steps = preemption.min_steps(T) if preemption is not None else T
        self.collected = 0
        for step in range(T):
            if should_stop():
                raise self._abandoned()
            if preemption is not None and step >= min_steps and preemption.preempted(self.update):
                break
            t0 = time.perf_counter()
            obs, hidden, masks = self.storage.current()
            actions, log_probs, values, new_hidden = self.policy.act(obs, hidden, masks)
            # labels of obs[t] from the privileged state, taken before the step (never shown to the policy)
            aux = rotation_labels(self.env).to(self.device) if self.cfg.aux_coef > 0 else None
            t1 = time.perf_counter()
            next_obs, rewards, done, infos = self.env.step(actions)
            t2 = time.perf_counter()
            t_forward += t1 - t0
            t_env += t2 - t1

            rewards = rewards.to(self.device, torch.float32)
            self.storage.insert(
                next_obs, new_hidden, actions, log_probs, values, rewards, self._masks(), aux_targets=aux
            )
            records += self._track_returns(rewards, done, infos)
            self.collected = step + 1
        if preemption is None:
            self.env_steps += distributed.global_steps(self.cfg.rollout_steps * self.env.num_envs)  # all ranks
        elif self.collected == T:
            preemption.finished(self.update)
        self._add_rollout_timings(t_forward, t_env, time.perf_counter() - start)
        return records

    @scoped(lambda self: self.policy.heavy)
    def train_update(self, should_stop: Callable[[], bool] = never) -> dict[str, Any]:
        """One rollout + one PPO update; returns PPO stats, level, env steps and the finished episodes.

        ``should_stop`` is polled before every rollout step; when it turns true the update is abandoned
        (:class:`UpdateAbandoned`) and :meth:`state_dict` describes the state before it. Once the rollout
        is complete the update always finishes.

        Raises ``FloatingPointError`` when the loss, the gradient or the updated weights are not finite
        (the storage is still advanced; do not save the policy after this).
        """
        self._begin_update()
        self.ppo.set_progress(self.update, self.total_updates)

        with no_distribution_validation():
            if self.preemption is None:
                records = self.collect_rollout(should_stop)
            else:
                records = self._collect_preemptible(should_stop)
            self._before_update = None
            with self._timed_update():
                obs, hidden, masks = self.storage.current()
                with torch.no_grad():
                    next_value = self.policy.get_value(obs, hidden, masks)
                try:
                    with _first_steps(self.storage, self.collected):
                        self.storage.values[self.collected].copy_(next_value)  # the bootstrap value of GAE
                        self.storage.compute_returns(next_value, self.cfg.gamma, self.cfg.gae_lambda)
                        stats: dict[str, Any] = self.ppo.update(self.storage, self.shuffle_generator)
                    self._check_weights(self.policy.parameters())
                finally:
                    self.storage.after_update()
        self.update += 1
        return self._finish_stats(stats, records)

    def _collect_preemptible(self, should_stop: Callable[[], bool]) -> list[dict[str, Any]]:
        """:meth:`collect_rollout` with straggler preemption; then every rank learns whether any rank
        abandoned the rollout (then all raise :class:`UpdateAbandoned`) and how many steps all collected."""
        abandoned, records = False, []
        try:
            records = self.collect_rollout(should_stop)
        except UpdateAbandoned:
            abandoned = True
        any_abandoned, steps = distributed.all_sum([float(abandoned), float(self.collected * self.env.num_envs)])
        if any_abandoned:
            raise self._abandoned()
        self.env_steps += int(steps)
        return records

    # ---------------------------------------------------------------------------------------------
    # Resume state (the common parts: Trainer)
    # ---------------------------------------------------------------------------------------------

    def _learner_parts(self) -> dict[str, Any]:
        """``ppo``: optimizer, lr / clip, the aux head and the initial policy of ``kl_to_init``."""
        return {"ppo": self.ppo.state_dict()}

    def _rollout_parts(self) -> dict[str, Any]:
        """``storage``: the rollout start (observation, GRU state, masks); ``shuffle_rng``."""
        return {"storage": self.storage.state_dict(), "shuffle_rng": self.shuffle_generator.get_state()}

    def _load_learner_parts(self, state: Mapping[str, Any]) -> None:
        self.ppo.load_state_dict(state["ppo"])

    def _load_rollout_parts(self, state: Mapping[str, Any]) -> None:
        if state.get("storage") is not None:
            self.storage.load_state_dict(state["storage"])
        if state.get("shuffle_rng") is not None:
            self.shuffle_generator.set_state(state["shuffle_rng"])
