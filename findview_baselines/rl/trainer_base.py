"""The skeleton every training algorithm shares, and the interface the run loop drives.

:class:`Trainer` is the base of :class:`~findview_baselines.rl.ppo_trainer.PPOTrainer` (``kind = "ppo"``) and
:class:`~findview_baselines.rl.dagger.DAggerTrainer` (``kind = "dagger"``). The training run loop uses
only what this class declares (no attribute probing)::

    trainer.start()                                   # fresh run: level, env reset
    trainer.load_state_dict(state, restore_rng=...)   # or resume (ValueError: another kind / model)
    stats = trainer.train_update(should_stop)         # one rollout + update; UpdateAbandoned on a stop
    trainer.state_dict()                              # the state before an abandoned update
    trainer.pop_timings()                             # seconds per phase (TIMING_KEYS) since the last call
    trainer.update, trainer.env_steps, trainer.policy, trainer.env, trainer.cfg
    trainer.steps_per_update                          # env steps of one update on this rank
    trainer.extra_modules()                           # modules besides the policy, identical on every rank
    trainer.supports_preemption / trainer.preemption  # straggler preemption (PPO only)

A subclass implements :meth:`Trainer.start`, :meth:`Trainer.train_update`, :meth:`Trainer.extra_modules`
and the four hooks of its own state parts (:meth:`Trainer._learner_parts`, :meth:`Trainer._rollout_parts`
and their loaders); the common parts (scheduler, counters, environment, episode returns, RNGs) and the
kind check live here.
"""

from __future__ import annotations

import abc
import contextlib
import time
from typing import Any, Callable, ClassVar, Iterable, Iterator, Mapping

import torch
from torch import nn
from torch.distributions import Distribution

from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import capture_rng_state, restore_rng_state
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.signature import check_signature

__all__ = ["TIMING_KEYS", "Trainer", "UpdateAbandoned", "never", "no_distribution_validation"]

#: the wall-clock phases of :attr:`Trainer.timings` / :meth:`Trainer.pop_timings` (seconds)
TIMING_KEYS = ("env_step", "policy_forward", "rollout_other", "update")


class UpdateAbandoned(Exception):
    """A stop was requested during the rollout; the update was not done (state: before it)."""


def never() -> bool:
    """The default ``should_stop``: never stop."""
    return False


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


class Trainer(abc.ABC):
    """Base of the training algorithms: shared state, bookkeeping and resume logic (see module docstring).

    Args:
        env: a batched, auto-resetting FindView environment (``num_envs``, ``reset``, ``step``,
            ``new_episode``; ``state_dict`` / ``load_state_dict`` when it can resume).
        policy: the :class:`Policy` (already on its device; :attr:`device` is taken from it).
        cfg: the algorithm's hyper-parameters (has ``rollout_steps``).
        total_updates: updates of the whole run (lr / clip decay, scheduler).
        scheduler: optional difficulty curriculum.
        set_level: called with the new level when the scheduler levels up (and at :meth:`start`).
    """

    #: the algorithm's name in ``trainer.algorithm`` and in :meth:`state_dict` (``"kind"``)
    kind: ClassVar[str]
    #: the algorithm's name in messages
    title: ClassVar[str]
    #: whether :attr:`preemption` (straggler preemption under torchrun) is honoured
    supports_preemption: ClassVar[bool] = False

    def __init__(
        self,
        env: Any,
        policy: Policy,
        cfg: Any,
        total_updates: int,
        scheduler: DifficultyScheduler | None = None,
        set_level: Callable[[int], None] | None = None,
    ) -> None:
        self.env = env
        self.policy = policy
        self.cfg = cfg
        self.total_updates = int(total_updates)
        self.scheduler = scheduler
        self.set_level = set_level
        self.device: torch.device = next(policy.parameters()).device
        self.update = 0  # index of the next update (= updates done)
        self.env_steps = 0  # env steps of all ranks
        self.episode_returns = torch.zeros(env.num_envs, device=self.device)  # (N,) reward sums so far
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)  # seconds per phase since pop_timings()
        self._before_update: dict[str, Any] | None = None  # resume parts while a rollout runs
        self.preemption: distributed.Preemption | None = None  # set by the run loop (supports_preemption only)

    # ---------------------------------------------------------------------------------------------
    # The interface of the run loop
    # ---------------------------------------------------------------------------------------------

    @abc.abstractmethod
    def start(self) -> None:
        """Fresh run: set the difficulty level for :attr:`update` and reset the environments."""

    @abc.abstractmethod
    def train_update(self, should_stop: Callable[[], bool] = never) -> dict[str, Any]:
        """One rollout + one update; returns the stats, with ``update``, ``env_steps``, ``level`` and
        ``episodes`` (the finished episodes' records, each with ``"return"``).

        ``should_stop`` is polled before every rollout step; when it turns true the update is abandoned
        (:class:`UpdateAbandoned`) and :meth:`state_dict` describes the state before it. Raises
        ``FloatingPointError`` when the loss, the gradient or the updated weights are not finite."""

    @abc.abstractmethod
    def extra_modules(self) -> list[nn.Module]:
        """Modules besides the policy whose weights must be identical on every rank (auxiliary heads)."""

    @property
    def steps_per_update(self) -> int:
        """Env steps of one (full) update on this rank: ``rollout_steps * num_envs``."""
        return int(self.cfg.rollout_steps) * int(self.env.num_envs)

    def pop_timings(self) -> dict[str, float]:
        """Seconds per phase since the last call (keys :data:`TIMING_KEYS`), then reset them."""
        out = dict(self.timings)
        self.timings = dict.fromkeys(TIMING_KEYS, 0.0)
        return out

    # ---------------------------------------------------------------------------------------------
    # Shared steps of the subclasses
    # ---------------------------------------------------------------------------------------------

    def _masks(self) -> torch.Tensor:
        """(N,) float on :attr:`device`: 0 where the env's current observation starts a new episode."""
        return (~self.env.new_episode).to(device=self.device, dtype=torch.float32)

    def _sync(self) -> None:
        """Wait for queued CUDA work so that wall-clock phase timings are attributed correctly."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _step_level(self, force: bool = False) -> None:
        """Step the scheduler to :attr:`update`; call ``set_level`` when the level changed (or ``force``)."""
        if self.scheduler is None:
            return
        changed = self.scheduler.step(self.update)
        if (changed or force) and self.set_level is not None:
            self.set_level(self.scheduler.current_level)

    def _begin_update(self) -> None:
        """Remember the state before the update (for an abandoned one), then step the level."""
        self._before_update = self._resume_parts()
        self._step_level()

    def _abandoned(self) -> UpdateAbandoned:
        """The exception of a stop request during the rollout of the update in flight."""
        return UpdateAbandoned(f"update {self.update + 1} abandoned during its rollout")

    def _track_returns(self, rewards: torch.Tensor, done: torch.Tensor, infos: list[Any]) -> list[dict[str, Any]]:
        """Add one step's ``rewards`` (N,) to :attr:`episode_returns`; return the records of the episodes
        that finished (``infos[i]`` not ``None``) with ``"return"`` (their undiscounted reward sum), and zero
        the sums where ``done`` (N,) bool."""
        self.episode_returns += rewards.to(self.device, torch.float32)
        finished = [i for i, info in enumerate(infos) if info is not None]
        records: list[dict[str, Any]] = []
        if finished:
            returns = self.episode_returns[finished].tolist()
            records = [{**infos[i], "return": r} for i, r in zip(finished, returns)]
        self.episode_returns.masked_fill_(done.to(self.device), 0.0)
        return records

    def _add_rollout_timings(self, forward: float, env: float, total: float) -> None:
        """Book a rollout's seconds: policy forward, env steps and the rest of ``total``."""
        self.timings["policy_forward"] += forward
        self.timings["env_step"] += env
        self.timings["rollout_other"] += total - forward - env

    @contextlib.contextmanager
    def _timed_update(self) -> Iterator[None]:
        """Book the block's seconds (after the queued CUDA work, also on an error) as ``update``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._sync()
            self.timings["update"] += time.perf_counter() - t0

    def _finish_stats(self, stats: dict[str, Any], records: list[dict[str, Any]]) -> dict[str, Any]:
        """Add the bookkeeping entries ``update``, ``env_steps``, ``level`` and ``episodes`` to ``stats``."""
        stats["update"] = self.update
        stats["env_steps"] = self.env_steps
        stats["level"] = self.scheduler.current_level if self.scheduler is not None else None
        stats["episodes"] = records
        return stats

    def _check_weights(self, params: Iterable[torch.Tensor]) -> None:
        """Raise ``FloatingPointError`` if any of ``params`` became NaN / inf (e.g. a NaN learning rate);
        the message names the policy's bad weights (else: an auxiliary head's)."""
        finite = torch.stack([torch.isfinite(p).all() for p in params]).all()
        if not bool(finite):
            bad = [name for name, p in self.policy.named_parameters() if not torch.isfinite(p).all()]
            raise FloatingPointError(f"non-finite weights after the optimizer step: {', '.join(bad[:5]) or 'aux head'}")

    # ---------------------------------------------------------------------------------------------
    # Resume state
    # ---------------------------------------------------------------------------------------------

    @abc.abstractmethod
    def _learner_parts(self) -> dict[str, Any]:
        """The subclass's state entries that an abandoned rollout leaves untouched (optimizer, ...)."""

    @abc.abstractmethod
    def _rollout_parts(self) -> dict[str, Any]:
        """The subclass's state entries that a rollout changes (current observation, its generators, ...)."""

    @abc.abstractmethod
    def _load_learner_parts(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`_learner_parts` (called after the policy weights are loaded)."""

    @abc.abstractmethod
    def _load_rollout_parts(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`_rollout_parts` (called after the environment; the global RNGs come last)."""

    def _check_state(self, state: Mapping[str, Any]) -> None:
        """Raise ``ValueError`` when ``state`` cannot be loaded; called before anything is loaded."""

    def _resume_parts(self) -> dict[str, Any]:
        """The parts of the resume state that a rollout changes (environment, rollout start, RNGs)."""
        return {
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else None,
            "env_steps": self.env_steps,
            "env": self.env.state_dict() if hasattr(self.env, "state_dict") else None,
            "episode_returns": self.episode_returns.cpu().clone(),
            "rng": capture_rng_state(),
            **self._rollout_parts(),
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (plain values + tensors: ``weights_only=True`` loads it).

        After an abandoned update (:class:`UpdateAbandoned`) the rollout parts describe the state before it
        (weights and optimizer are unchanged by a rollout)."""
        parts = self._before_update if self._before_update is not None else self._resume_parts()
        return {
            "kind": self.kind,
            "signature": self.policy.model_signature(),
            "policy": self.policy.state_dict(),
            **self._learner_parts(),
            "update": self.update,
            **parts,
        }

    def load_state_dict(self, state: Mapping[str, Any], restore_rng: bool = True) -> None:
        """Resume from :meth:`state_dict`. Raises ``ValueError`` on a state of another kind of trainer (a
        state without ``"kind"`` is a PPO one: saved before the key existed) or a model mismatch.

        When the state holds the environment and the rollout state, the environment continues its running
        episodes and no :meth:`start` is needed; otherwise call :meth:`start` afterwards. ``restore_rng``:
        also restore torch / numpy / Python RNGs (do it last, after building everything else)."""
        saved = state.get("kind", "ppo")
        if saved != self.kind:
            raise ValueError(f"this trainer state was not saved by the {self.title} trainer (trainer={self.kind}) "
                             f"but by the {saved!r} one")
        check_signature(state["signature"], self.policy.model_signature())
        self._check_state(state)
        self.policy.load_state_dict(state["policy"])
        self._load_learner_parts(state)
        if self.scheduler is not None and state.get("scheduler") is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        self.update = int(state["update"])
        self.env_steps = int(state["env_steps"])
        env_state = state.get("env")
        if env_state is not None and hasattr(self.env, "load_state_dict"):
            self.env.load_state_dict(env_state)
        if state.get("episode_returns") is not None:
            self.episode_returns.copy_(state["episode_returns"])
        self._load_rollout_parts(state)
        if restore_rng and state.get("rng") is not None:
            restore_rng_state(state["rng"])
