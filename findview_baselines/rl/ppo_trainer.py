"""The PPO update loop: collect ``rollout_steps`` steps of every environment, then one PPO update.

The environment follows the ``findview.task.FindViewEnv`` contract (docs/ARCHITECTURE.md)::

    obs = env.reset()                                  # {"view", "target"}: (N, 3, H, W) uint8
    obs, reward, done, infos = env.step(actions)       # reward (N,), done (N,) bool, infos[i] record or None
    env.new_episode                                    # (N,) bool: obs[i] starts an episode -> mask 0

:class:`PPOTrainer` is one *algorithm* of the run loop (:mod:`findview_baselines.rl.run`); every
algorithm has the same interface: ``start()``, ``train_update(should_stop) -> stats``,
``state_dict()`` / ``load_state_dict()``, ``pop_timings()`` and the attributes ``update``,
``env_steps``, ``policy``, ``env``.

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
from torch.distributions import Distribution

from findview.task.oracle import rotation_labels
from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import capture_rng_state, restore_rng_state
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.signature import check_signature
from findview_baselines.rl.storage import RolloutStorage

__all__ = ["PPOTrainer", "UpdateAbandoned", "no_distribution_validation", "TIMING_KEYS"]


class UpdateAbandoned(Exception):
    """A stop was requested during the rollout; the update was not done (state: before it)."""


def _never() -> bool:
    return False


TIMING_KEYS = ("env_step", "policy_forward", "rollout_other", "update")


def _masks(env: Any, device: torch.device) -> torch.Tensor:
    """(N,) float: 0 where the env's current observation starts a new episode."""
    return (~env.new_episode).to(device=device, dtype=torch.float32)


@contextlib.contextmanager
def no_distribution_validation() -> Iterator[None]:
    """Turn off ``torch.distributions`` argument checks (speed; and NaN logits then surface as a non-finite
    PPO loss, i.e. ``FloatingPointError``, instead of a ``ValueError`` from ``Categorical``)."""
    previous = Distribution._validate_args
    Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        Distribution.set_default_validate_args(previous)


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


def _sync(device: torch.device) -> None:
    """Wait for queued CUDA work so that wall-clock phase timings are attributed correctly."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


# --------------------------------------------------------------------------------------------------
# The update loop
# --------------------------------------------------------------------------------------------------


class PPOTrainer:
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
        self.env = env
        self.policy = policy
        self.cfg = cfg
        self.total_updates = total_updates
        self.scheduler = scheduler
        self.set_level = set_level
        self.device = next(policy.parameters()).device
        self.ppo = PPO(policy, cfg)
        self.storage = RolloutStorage(
            cfg.rollout_steps, env.num_envs, policy.height, policy.width, policy.hidden_size, self.device
        )
        self.shuffle_generator = torch.Generator().manual_seed(seed)
        self.update = 0  # index of the next update (= updates done)
        self.env_steps = 0
        self.episode_returns = torch.zeros(env.num_envs, device=self.device)
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        self._before_update: dict[str, Any] | None = None  # resume parts while a rollout runs
        self.preemption: distributed.Preemption | None = None  # straggler preemption (set by the run loop)
        self.collected = cfg.rollout_steps  # steps of the last rollout (fewer when preempted)

    # ---------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Fresh run: set the difficulty level for ``self.update`` and reset the environments."""
        if self.scheduler is not None:
            self.scheduler.step(self.update)
            if self.set_level is not None:
                self.set_level(self.scheduler.current_level)
        obs = self.env.reset()
        self.storage.set_initial(obs, _masks(self.env, self.device))
        self.episode_returns.zero_()

    @torch.no_grad()
    def collect_rollout(self, should_stop: Callable[[], bool] = _never) -> list[dict[str, Any]]:
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
                raise UpdateAbandoned(f"update {self.update + 1} abandoned during its rollout")
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
                next_obs, new_hidden, actions, log_probs, values, rewards, _masks(self.env, self.device), aux_targets=aux
            )
            self.episode_returns += rewards
            finished = [i for i, info in enumerate(infos) if info is not None]
            if finished:
                returns = self.episode_returns[finished].tolist()
                records += [{**infos[i], "return": r} for i, r in zip(finished, returns)]
            self.episode_returns.masked_fill_(done.to(self.device), 0.0)
            self.collected = step + 1
        if preemption is None:
            self.env_steps += distributed.global_steps(self.cfg.rollout_steps * self.env.num_envs)  # all ranks
        elif self.collected == T:
            preemption.finished(self.update)
        total = time.perf_counter() - start
        self.timings["policy_forward"] += t_forward
        self.timings["env_step"] += t_env
        self.timings["rollout_other"] += total - t_forward - t_env
        return records

    def train_update(self, should_stop: Callable[[], bool] = _never) -> dict[str, Any]:
        """One rollout + one PPO update; returns PPO stats, level, env steps and the finished episodes.

        ``should_stop`` is polled before every rollout step; when it turns true the update is abandoned
        (:class:`UpdateAbandoned`) and :meth:`state_dict` describes the state before it. Once the rollout
        is complete the update always finishes.

        Raises ``FloatingPointError`` when the loss, the gradient or the updated weights are not finite
        (the storage is still advanced; do not save the policy after this).
        """
        self._before_update = self._resume_parts()
        if self.scheduler is not None and self.scheduler.step(self.update) and self.set_level is not None:
            self.set_level(self.scheduler.current_level)
        self.ppo.set_progress(self.update, self.total_updates)

        with no_distribution_validation():
            if self.preemption is None:
                records = self.collect_rollout(should_stop)
            else:
                records = self._collect_preemptible(should_stop)
            self._before_update = None
            t0 = time.perf_counter()
            obs, hidden, masks = self.storage.current()
            with torch.no_grad():
                next_value = self.policy.get_value(obs, hidden, masks)
            try:
                with _first_steps(self.storage, self.collected):
                    self.storage.values[self.collected].copy_(next_value)  # the bootstrap value of GAE
                    self.storage.compute_returns(next_value, self.cfg.gamma, self.cfg.gae_lambda)
                    stats: dict[str, Any] = self.ppo.update(self.storage, self.shuffle_generator)
                self._check_weights()
            finally:
                self.storage.after_update()
                _sync(self.device)
                self.timings["update"] += time.perf_counter() - t0
        self.update += 1

        stats["update"] = self.update
        stats["env_steps"] = self.env_steps
        stats["level"] = self.scheduler.current_level if self.scheduler is not None else None
        stats["episodes"] = records
        return stats

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
            raise UpdateAbandoned(f"update {self.update + 1} abandoned during its rollout")
        self.env_steps += int(steps)
        return records

    def _check_weights(self) -> None:
        """Raise ``FloatingPointError`` if any weight became NaN / inf (e.g. a NaN learning rate)."""
        finite = torch.stack([torch.isfinite(p).all() for p in self.policy.parameters()]).all()
        if not bool(finite):
            bad = [name for name, p in self.policy.named_parameters() if not torch.isfinite(p).all()]
            raise FloatingPointError(f"non-finite weights after the optimizer step: {', '.join(bad[:5])}")

    def pop_timings(self) -> dict[str, float]:
        """Seconds per phase since the last call (keys :data:`TIMING_KEYS`), then reset them."""
        out = dict(self.timings)
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        return out

    # ---------------------------------------------------------------------------------------------
    # Resume state
    # ---------------------------------------------------------------------------------------------

    def _resume_parts(self) -> dict[str, Any]:
        """The parts of the resume state that a rollout changes (environment, rollout start, RNGs)."""
        return {
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else None,
            "env_steps": self.env_steps,
            "env": self.env.state_dict() if hasattr(self.env, "state_dict") else None,
            "storage": self.storage.state_dict(),
            "episode_returns": self.episode_returns.cpu().clone(),
            "shuffle_rng": self.shuffle_generator.get_state(),
            "rng": capture_rng_state(),
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (plain values + tensors: ``weights_only=True`` loads it).

        Includes the environment's state (when it has ``state_dict``), the rollout storage's initial
        observation / hidden state / masks and every RNG state. After an abandoned update
        (:class:`UpdateAbandoned`) these describe the state before that update (weights and optimizer
        are unchanged by a rollout).
        """
        parts = self._before_update if self._before_update is not None else self._resume_parts()
        return {
            "signature": self.policy.model_signature(),
            "policy": self.policy.state_dict(),
            "ppo": self.ppo.state_dict(),
            "update": self.update,
            **parts,
        }

    def load_state_dict(self, state: Mapping[str, Any], restore_rng: bool = True) -> None:
        """Resume from :meth:`state_dict`. Raises ``ValueError`` on a model mismatch.

        When the state holds the environment and the rollout state (a full checkpoint of a FindView env),
        the environment continues its running episodes and no :meth:`start` is needed; otherwise call
        :meth:`start` afterwards. ``restore_rng``: also restore torch / numpy / Python RNGs (do it last,
        after building everything else, so that construction does not disturb them).
        """
        check_signature(state["signature"], self.policy.model_signature())
        self.policy.load_state_dict(state["policy"])
        self.ppo.load_state_dict(state["ppo"])
        if self.scheduler is not None and state.get("scheduler") is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        self.update = int(state["update"])
        self.env_steps = int(state["env_steps"])

        env_state = state.get("env")
        if env_state is not None and hasattr(self.env, "load_state_dict"):
            self.env.load_state_dict(env_state)
        saved = state.get("storage")
        if saved is not None:
            self.storage.load_state_dict(saved)
        if state.get("episode_returns") is not None:
            self.episode_returns.copy_(state["episode_returns"])
        if state.get("shuffle_rng") is not None:
            self.shuffle_generator.set_state(state["shuffle_rng"])
        if restore_rng and state.get("rng") is not None:
            restore_rng_state(state["rng"])


