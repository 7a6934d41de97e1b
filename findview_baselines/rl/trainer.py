"""PPO training: the update loop (:class:`PPOTrainer`), greedy evaluation, checkpoints and the whole run
driven by ``tools/train.py`` (:func:`train`).

The environment follows the ``findview.task.FindViewEnv`` contract (docs/ARCHITECTURE.md)::

    obs = env.reset()                                  # {"view", "target"}: (N, 3, H, W) uint8
    obs, reward, done, infos = env.step(actions)       # reward (N,), done (N,) bool, infos[i] record or None
    env.new_episode                                    # (N,) bool: obs[i] starts an episode -> mask 0
    env.active                                         # (N,) bool: slot still runs an episode (static sources)

A run (:func:`train`) in ``run_dir``::

    run_dir/
      .hydra/                 # Hydra's composed config (when started by tools/train.py)
      resolved_config.yaml    # the resolved config of the latest (re)start
      checkpoints/latest.pth  # everything needed to resume exactly (written every checkpoint_interval)
      checkpoints/best.pth    # weights + config of the lowest mean val eps so far
      tb/                     # TensorBoard scalars (global step = updates done)

Re-running with the same ``run_dir`` and ``trainer.resume=true`` continues from ``latest.pth``: same
weights, optimizer, lr / clip position, difficulty level, RNG states, running episodes and rollout
state, so N updates in one go and N/2 + resume + N/2 give the same weights (on CPU).
"""

from __future__ import annotations

import contextlib
import logging
import math
import random
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np
import torch
from torch.distributions import Distribution

from findview_baselines.rl.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    ResumableSampler,
    capture_rng_state,
    check_writable,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from findview_baselines.rl.policy import Policy, build_policy, check_signature
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import RolloutStorage

log = logging.getLogger(__name__)

__all__ = [
    "PPOTrainer",
    "TrainingDiverged",
    "TrainResult",
    "evaluate",
    "load_policy",
    "save_checkpoint",
    "select_val_episodes",
    "train",
]

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
    def collect_rollout(self) -> list[dict[str, Any]]:
        """Run ``rollout_steps`` steps, filling the storage; returns the records of finished episodes
        (each with an extra ``"return"``: the undiscounted reward sum)."""
        records: list[dict[str, Any]] = []
        self.policy.eval()
        t_forward = t_env = 0.0
        start = time.perf_counter()
        for _ in range(self.cfg.rollout_steps):
            t0 = time.perf_counter()
            obs, hidden, masks = self.storage.current()
            actions, log_probs, values, new_hidden = self.policy.act(obs, hidden, masks)
            _sync(self.device)
            t1 = time.perf_counter()
            next_obs, rewards, done, infos = self.env.step(actions)
            t2 = time.perf_counter()
            t_forward += t1 - t0
            t_env += t2 - t1

            rewards = rewards.to(self.device, torch.float32)
            self.storage.insert(
                next_obs, new_hidden, actions, log_probs, values, rewards, _masks(self.env, self.device)
            )
            self.episode_returns += rewards
            finished = [i for i, info in enumerate(infos) if info is not None]
            if finished:
                returns = self.episode_returns.tolist()
                records += [{**infos[i], "return": returns[i]} for i in finished]
            self.episode_returns[done.to(self.device)] = 0.0
        self.env_steps += self.cfg.rollout_steps * self.env.num_envs
        total = time.perf_counter() - start
        self.timings["policy_forward"] += t_forward
        self.timings["env_step"] += t_env
        self.timings["rollout_other"] += total - t_forward - t_env
        return records

    def train_update(self) -> dict[str, Any]:
        """One rollout + one PPO update; returns PPO stats, level, env steps and the finished episodes.

        Raises ``FloatingPointError`` when the loss, the gradient or the updated weights are not finite
        (the storage is still advanced; do not save the policy after this).
        """
        if self.scheduler is not None and self.scheduler.step(self.update) and self.set_level is not None:
            self.set_level(self.scheduler.current_level)
        self.ppo.set_progress(self.update, self.total_updates)

        with no_distribution_validation():
            records = self.collect_rollout()
            t0 = time.perf_counter()
            obs, hidden, masks = self.storage.current()
            with torch.no_grad():
                next_value = self.policy.get_value(obs, hidden, masks)
            self.storage.compute_returns(next_value, self.cfg.gamma, self.cfg.gae_lambda)
            try:
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

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly (plain values + tensors: ``weights_only=True`` loads it).

        Includes the environment's state (when it has ``state_dict``), the rollout storage's initial
        observation / hidden state / masks and every RNG state.
        """
        s = self.storage
        return {
            "signature": self.policy.model_signature(),
            "policy": self.policy.state_dict(),
            "ppo": self.ppo.state_dict(),
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else None,
            "update": self.update,
            "env_steps": self.env_steps,
            "env": self.env.state_dict() if hasattr(self.env, "state_dict") else None,
            "storage": {
                "view": s.view[0].cpu().clone(),
                "target": s.target[0].cpu().clone(),
                "hidden": s.hidden[0].cpu().clone(),
                "masks": s.masks[0].cpu().clone(),
            },
            "episode_returns": self.episode_returns.cpu().clone(),
            "shuffle_rng": self.shuffle_generator.get_state(),
            "rng": capture_rng_state(),
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
            s = self.storage
            s.view[0].copy_(saved["view"])
            s.target[0].copy_(saved["target"])
            s.hidden[0].copy_(saved["hidden"])
            s.masks[0].copy_(saved["masks"])
            s.step = 0
        if state.get("episode_returns") is not None:
            self.episode_returns.copy_(state["episode_returns"])
        if state.get("shuffle_rng") is not None:
            self.shuffle_generator.set_state(state["shuffle_rng"])
        if restore_rng and state.get("rng") is not None:
            restore_rng_state(state["rng"])


# --------------------------------------------------------------------------------------------------
# Evaluation and loading
# --------------------------------------------------------------------------------------------------


def load_policy(path: str | Path, policy: Policy) -> dict[str, Any]:
    """Load the weights of a checkpoint into ``policy`` after checking its signature; returns the checkpoint.

    Loads with ``weights_only=True``. Raises ``ValueError`` naming the file and the first differing model
    field (``variant``, ``hidden_size``, ``height``, ``width``).
    """
    state = load_checkpoint(path, map_location=next(policy.parameters()).device)
    try:
        check_signature(state["signature"], policy.model_signature())
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    policy.load_state_dict(state["policy"])
    return state


@torch.no_grad()
def evaluate(env: Any, policy: Policy, deterministic: bool = True) -> list[dict[str, Any]]:
    """Run ``policy`` until every slot of ``env`` (a static episode source) is exhausted.

    Returns the episode records, in order of completion.
    """
    device = next(policy.parameters()).device
    policy.eval()
    obs = env.reset()
    hidden = policy.initial_hidden(env.num_envs, device)
    records: list[dict[str, Any]] = []
    with no_distribution_validation():
        while bool(env.active.any()):
            obs = {key: value.to(device) for key, value in obs.items()}
            actions, _, _, hidden = policy.act(obs, hidden, _masks(env, device), deterministic=deterministic)
            obs, _, _, infos = env.step(actions)
            records += [info for info in infos if info is not None]
    return records


def select_val_episodes(episodes: Sequence[Any], cap: int | None) -> list[Any]:
    """At most ``cap`` episodes, spread evenly over the difficulties present and, within one, over the list.

    ``cap=None`` (or a cap above the count) keeps all. Order: difficulty groups in first-seen order.
    """
    episodes = list(episodes)
    if cap is None or int(cap) >= len(episodes):
        return episodes
    cap = int(cap)
    if cap <= 0:
        raise ValueError(f"trainer.val_episodes must be positive or null, got {cap}")
    groups: dict[str, list[Any]] = {}
    for ep in episodes:
        groups.setdefault(ep.difficulty, []).append(ep)
    names = list(groups)
    out: list[Any] = []
    for k, name in enumerate(names):
        group = groups[name]
        n = min(len(group), cap // len(names) + (1 if k < cap % len(names) else 0))
        out += [group[i * len(group) // n] for i in range(n)]
    return out


# --------------------------------------------------------------------------------------------------
# The whole run (tools/train.py)
# --------------------------------------------------------------------------------------------------


class TrainingDiverged(RuntimeError):
    """A non-finite loss / gradient / weight stopped training; the last good checkpoint was kept."""


@dataclass
class TrainResult:
    """What :func:`train` did."""

    run_dir: Path
    updates: int  # updates done in total (including earlier sessions)
    env_steps: int
    completed: bool  # reached trainer.num_updates
    latest: Path | None  # checkpoints/latest.pth if written
    best: Path | None  # checkpoints/best.pth if any validation ran
    best_val_eps: float | None
    last_val: dict[str, dict[str, float]] | None  # metrics.summarize(..., include_all=True) of the last validation
    steps_per_second: float  # env steps / s of this session's training (validation excluded)


def _plain(cfg: Any) -> dict[str, Any]:
    """A plain, resolved ``dict`` copy of a Hydra / OmegaConf or mapping config."""
    try:
        from omegaconf import DictConfig, OmegaConf

        if isinstance(cfg, DictConfig):
            return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except ImportError:  # pragma: no cover - omegaconf is a requirement
        pass

    def convert(x: Any) -> Any:
        if isinstance(x, Mapping):
            return {str(k): convert(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [convert(v) for v in x]
        return x

    return convert(cfg)


def _get(section: Mapping[str, Any] | None, key: str, default: Any = None) -> Any:
    """``section[key]`` or ``default`` when the section / key is missing or null."""
    if not section:
        return default
    value = section.get(key, default)
    return default if value is None else value


def _check_trainer_config(t: Mapping[str, Any]) -> None:
    """Raise ``ValueError`` naming a bad ``trainer.*`` value."""
    for key in ("num_updates", "num_envs"):
        value = t.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"trainer.{key} must be a positive integer, got {value!r}")
    for key in ("val_interval", "log_interval", "checkpoint_interval", "val_episodes", "val_num_envs", "stop_after",
                "torch_threads"):
        value = t.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            raise ValueError(f"trainer.{key} must be a non-negative integer or null, got {value!r}")


def seed_everything(seed: int) -> None:
    """Seed torch (CPU + CUDA), numpy's global RNG and Python's ``random``."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _hard_rule(conf: Mapping[str, Any]) -> str:
    """The hard-difficulty rule (``or`` | ``and``) from the dataset or task config (default ``or``)."""
    return str(_get(conf.get("dataset"), "hard_rule", None) or _get(conf.get("task"), "hard_rule", "or"))


class _GracefulStop:
    """First Ctrl-C asks the loop to stop after the current update (checkpoint written); the second one
    interrupts at once. Only active in the main thread."""

    def __init__(self) -> None:
        self.requested = False
        self._previous: Any = None

    def __enter__(self) -> "_GracefulStop":
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("Ctrl-C: stopping after this update and writing latest.pth (press again to abort now)")

    def __exit__(self, *exc: Any) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


class _MetricWindow:
    """Recent finished training episodes (for the progress bar and TensorBoard)."""

    def __init__(self, size: int) -> None:
        self.records: deque[dict[str, Any]] = deque(maxlen=size)

    def add(self, records: Sequence[Mapping[str, Any]]) -> None:
        self.records.extend(dict(r) for r in records)

    def summary(self) -> dict[str, float]:
        if not self.records:
            return {}
        n = len(self.records)
        mean = lambda key: sum(float(r.get(key, 0.0)) for r in self.records) / n  # noqa: E731
        stopped = [bool(r.get("called_stop", False)) for r in self.records]
        success = [s and float(r.get("eps", 1.0)) == 0.0 for s, r in zip(stopped, self.records)]
        return {
            "reward": mean("return"),
            "eps": mean("eps"),
            "episode_length": mean("steps"),
            "omega_stop": sum(stopped) / n,
            "success_rate": sum(success) / n,
        }


def _build_data(
    conf: Mapping[str, Any], dataset_cfg: Any, need_val: bool, progress: bool
) -> tuple[list[Any], list[Any]]:
    """(train images, val episodes) of the configured dataset; makes the dataset files if missing."""
    from findview.dataset import ensure_dataset, episode_file, load_episodes, load_split

    fov = float(conf["sim"]["fov"])
    task = conf.get("task") or {}
    out_dir = ensure_dataset(
        dataset_cfg,
        [fov],
        pitch_bound=int(_get(task, "pitch_bound", 60)),
        max_steps=int(_get(task, "max_steps", 5000)),
        progress=progress,
        log=log.info,
    )
    train_images = load_split(out_dir, "train")
    if not train_images:
        raise ValueError(f"the train split of dataset {conf['dataset'].get('name')!r} in {out_dir} is empty")
    val_episodes = load_episodes(episode_file(out_dir, "val", fov)) if need_val else []
    return train_images, val_episodes


def train(cfg: Any, run_dir: str | Path, progress: bool | None = None) -> TrainResult:
    """Train (or resume) the PPO agent described by ``cfg`` (the ``configs/train.yaml`` tree) in ``run_dir``.

    Args:
        cfg: Hydra ``DictConfig`` or a plain mapping with ``dataset, sim, task, agent, trainer, scheduler,
            init_from``.
        run_dir: the run's folder (checkpoints, TensorBoard, config copy). Checked for write access first.
        progress: show the tqdm bar (default ``trainer.progress``).

    Raises:
        PermissionError: ``run_dir`` is not writable (before anything else happens).
        ValueError: a bad config value, or ``init_from`` / ``latest.pth`` not fitting the model (naming
            the field).
        TrainingDiverged: a non-finite loss / weight; names the update; ``latest.pth`` keeps the last good state.
    """
    run_dir = check_writable(run_dir, "run folder")
    ckpt_dir = check_writable(run_dir / "checkpoints", "checkpoint folder")
    conf = _plain(cfg)
    dataset_cfg = cfg["dataset"]
    t = dict(conf.get("trainer") or {})
    t.setdefault("num_updates", 30000)
    t.setdefault("num_envs", 16)
    _check_trainer_config(t)
    num_updates = int(t["num_updates"])
    num_envs = int(t["num_envs"])
    seed = int(_get(t, "seed", 0))
    val_interval = int(_get(t, "val_interval", 0))
    val_at_end = bool(_get(t, "val_at_end", True))
    log_interval = max(1, int(_get(t, "log_interval", 10)))
    ckpt_interval = int(_get(t, "checkpoint_interval", 100))
    stop_after = t.get("stop_after")
    show_progress = bool(_get(t, "progress", True)) if progress is None else progress
    sched_cfg = conf.get("scheduler") or {}
    sim_cfg, task_cfg, agent_cfg = conf["sim"], conf["task"], conf["agent"]
    latest_path, best_path = ckpt_dir / "latest.pth", ckpt_dir / "best.pth"

    # ---- resume or fresh start ------------------------------------------------------------------
    resume_state: dict[str, Any] | None = None
    if bool(_get(t, "resume", True)) and latest_path.is_file():
        resume_state = load_checkpoint(latest_path)
        if resume_state.get("trainer") is None:
            raise ValueError(f"{latest_path} holds no trainer state; it cannot be resumed")
        _warn_config_changes(resume_state.get("config") or {}, conf)
    elif latest_path.is_file():
        log.warning("trainer.resume=false: starting over in %s (the old latest.pth will be overwritten)", run_dir)

    threads = t.get("torch_threads")
    previous_threads = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    try:
        with no_distribution_validation(), _GracefulStop() as graceful:
            return _run(
                conf, dataset_cfg, run_dir, latest_path, best_path, resume_state, graceful,
                num_updates=num_updates, num_envs=num_envs, seed=seed, val_interval=val_interval,
                val_at_end=val_at_end, log_interval=log_interval, ckpt_interval=ckpt_interval,
                stop_after=stop_after, show_progress=show_progress, sched_cfg=sched_cfg, sim_cfg=sim_cfg,
                task_cfg=task_cfg, agent_cfg=agent_cfg, t=t,
            )
    finally:
        torch.set_num_threads(previous_threads)


def _warn_config_changes(saved: Mapping[str, Any], current: Mapping[str, Any], prefix: str = "") -> None:
    """Log the config values that differ between a checkpoint and the current run (resume keeps going)."""
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            _warn_config_changes(a, b, f"{prefix}{key}.")
        elif a != b and key not in ("resume", "progress", "stop_after"):
            log.warning("resuming with a changed config value %s%s: %r -> %r", prefix, key, a, b)


def _run(
    conf: dict[str, Any],
    dataset_cfg: Any,
    run_dir: Path,
    latest_path: Path,
    best_path: Path,
    resume_state: dict[str, Any] | None,
    graceful: _GracefulStop,
    *,
    num_updates: int,
    num_envs: int,
    seed: int,
    val_interval: int,
    val_at_end: bool,
    log_interval: int,
    ckpt_interval: int,
    stop_after: int | None,
    show_progress: bool,
    sched_cfg: Mapping[str, Any],
    sim_cfg: Mapping[str, Any],
    task_cfg: Mapping[str, Any],
    agent_cfg: Mapping[str, Any],
    t: Mapping[str, Any],
) -> TrainResult:
    """The body of :func:`train` (arguments already checked)."""
    from omegaconf import OmegaConf
    from torch.utils.tensorboard import SummaryWriter
    from tqdm import tqdm

    from findview.dataset import EpisodeSampler
    from findview.metrics import summarize
    from findview.sim import PanoramaBank, Simulator, resolve_device
    from findview.task import FindViewEnv
    from findview.task.rewards import RewardConfig
    from findview.task.sources import SampledEpisodeSource, StaticEpisodeSource

    seed_everything(seed)
    need_val = val_at_end or val_interval > 0
    train_images, val_all = _build_data(conf, dataset_cfg, need_val, show_progress)
    val_episodes = select_val_episodes(val_all, t.get("val_episodes"))
    if need_val and not val_episodes:
        log.warning("no val episodes: validation and best.pth are skipped")

    # ---- simulator, environments, policy ---------------------------------------------------------
    device = resolve_device(_get(sim_cfg, "device", "auto"))
    height, width, fov = int(sim_cfg["height"]), int(sim_cfg["width"]), float(sim_cfg["fov"])
    max_steps = int(_get(task_cfg, "max_steps", 5000))
    pitch_bound = int(_get(task_cfg, "pitch_bound", 60))
    val_envs = min(int(_get(t, "val_num_envs", num_envs)), len(val_episodes)) if val_episodes else 0
    images = {im.path for im in train_images} | {ep.image for ep in val_episodes}
    bank = PanoramaBank(
        device,
        budget_mb=float(_get(sim_cfg, "bank_mb", 2048)),
        equi_height=sim_cfg.get("equi_height"),
        prefetch_workers=int(_get(sim_cfg, "prefetch_workers", 2)),
        max_panoramas=len(images),
        min_slots=num_envs + val_envs,
    )
    sim = Simulator(
        bank, fov=fov, height=height, width=width, pitch_bound=pitch_bound,
        mode=str(_get(sim_cfg, "mode", "bilinear")), backend=str(_get(sim_cfg, "backend", "auto")),
    )
    reward = RewardConfig(**dict(task_cfg.get("reward") or {}))
    env_kwargs = dict(max_steps=max_steps, pitch_bound=pitch_bound, step_deg=int(_get(task_cfg, "step_deg", 1)), reward=reward)
    sampler = ResumableSampler(
        EpisodeSampler(train_images, fov, seed=seed, pitch_bound=pitch_bound, max_steps=max_steps, hard_rule=_hard_rule(conf))
    )
    source = SampledEpisodeSource(sampler, level=1)
    env = FindViewEnv(sim, source, num_envs, auto_reset=True, **env_kwargs)
    val_env = (
        FindViewEnv(sim, StaticEpisodeSource(val_episodes), val_envs, auto_reset=True, **env_kwargs)
        if val_episodes
        else None
    )

    policy = build_policy(agent_cfg, height, width).to(device)
    ppo_cfg = PPOConfig.from_mapping(agent_cfg)
    scheduler = DifficultyScheduler(
        num_updates, num_levels=int(_get(sched_cfg, "num_levels", 3)), mode=str(_get(sched_cfg, "mode", "unbounded"))
    )
    if scheduler.mode == "bounded":
        set_level: Callable[[int], None] = _bounded_level_setter(source, scheduler)
    else:
        set_level = lambda k: setattr(source, "level", k)  # noqa: E731
    trainer = PPOTrainer(env, policy, ppo_cfg, num_updates, scheduler, set_level, seed=seed)

    best_val_eps: float | None = None
    last_val: dict[str, Any] | None = None
    if resume_state is not None:
        trainer.load_state_dict(resume_state["trainer"], restore_rng=False)
        best_val_eps = resume_state.get("best_val_eps")
        last_val = resume_state.get("val")
        log.info("resumed %s at update %d (%d env steps)", run_dir, trainer.update, trainer.env_steps)
    else:
        init_from = conf.get("init_from")
        if init_from:
            state = load_policy(Path(str(init_from)).expanduser(), policy)
            log.info("initialised the weights from %s (update %s of that run); fresh optimizer", init_from, state.get("update"))
        trainer.start()

    # resolved config beside Hydra's .hydra/ (tests and API users have no Hydra)
    (run_dir / "resolved_config.yaml").write_text(OmegaConf.to_yaml(OmegaConf.create(conf)))

    def checkpoint(val: dict[str, Any] | None, with_trainer: bool) -> dict[str, Any]:
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "signature": policy.model_signature(),
            "policy": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
            "update": trainer.update,
            "env_steps": trainer.env_steps,
            "config": conf,
            "val": val,
            "best_val_eps": best_val_eps,
            "trainer": trainer.state_dict() if with_trainer else None,
        }

    def validate() -> dict[str, Any]:
        assert val_env is not None
        val_env.source.load_state_dict({"index": 0})
        start = time.perf_counter()
        records = evaluate(val_env, policy, deterministic=bool(_get(agent_cfg, "deterministic_eval", True)))
        result = summarize(records, include_all=True)
        log.info(
            "val at update %d (%d episodes, %.1fs): %s", trainer.update, len(records), time.perf_counter() - start,
            ", ".join(f"{d} eps {m['eps']:.2f} stop {m['omega_stop']:.2f} spl {m['spl']:.2f}" for d, m in result.items()),
        )
        return result

    if resume_state is not None:
        restore_rng_state(resume_state["trainer"]["rng"])  # last: building the run consumed random numbers

    writer = SummaryWriter(log_dir=str(run_dir / "tb"), purge_step=trainer.update + 1 if resume_state else 0)
    window = _MetricWindow(size=max(100, 4 * num_envs))
    totals: dict[str, float] = {}
    count = 0
    session_start_update, session_steps, session_time = trainer.update, 0, 0.0
    interval_start, interval_steps = time.perf_counter(), 0
    last_saved_update = trainer.update if resume_state is not None else -1
    stop_at = num_updates if stop_after is None else min(num_updates, trainer.update + int(stop_after))
    if trainer.update >= num_updates:
        log.info("run %s is already complete (%d updates); nothing to do", run_dir, trainer.update)

    bar = tqdm(total=num_updates, initial=trainer.update, unit="upd", dynamic_ncols=True, disable=not show_progress)
    try:
        while trainer.update < stop_at and not graceful.requested:
            t0 = time.perf_counter()
            try:
                stats = trainer.train_update()
            except FloatingPointError as err:
                kept = (
                    f"the last good checkpoint {latest_path} (update {last_saved_update}) was kept"
                    if latest_path.is_file() and last_saved_update >= 0
                    else "no checkpoint had been written yet"
                )
                raise TrainingDiverged(
                    f"training diverged at update {trainer.update + 1}: {err}; training stopped and {kept}. "
                    f"Lower agent.lr or check the inputs, then re-run to resume from the last checkpoint."
                ) from err
            dt = time.perf_counter() - t0
            steps = ppo_cfg.rollout_steps * num_envs
            session_steps += steps
            session_time += dt
            interval_steps += steps
            update = trainer.update
            window.add(stats["episodes"])
            for key in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "grad_norm"):
                totals[key] = totals.get(key, 0.0) + float(stats[key])
            count += 1
            recent = window.summary()
            bar.update(1)
            bar.set_postfix(
                sps=f"{steps / dt:.0f}", lvl=stats["level"],
                R=f"{recent.get('reward', float('nan')):.2f}",
                eps=f"{recent.get('eps', float('nan')):.1f}",
                succ=f"{recent.get('success_rate', float('nan')):.2f}",
                refresh=False,
            )

            if update % log_interval == 0 or update == stop_at:
                elapsed = time.perf_counter() - interval_start
                timings = trainer.pop_timings()
                scalars = {f"loss/{k}": v / count for k, v in totals.items()}
                scalars.update({f"train/{k}": v for k, v in recent.items()})
                scalars.update({
                    "schedule/lr": stats["lr"], "schedule/clip": stats["clip"], "schedule/level": float(stats["level"]),
                    "perf/fps": interval_steps / max(elapsed, 1e-9), "perf/env_steps": float(trainer.env_steps),
                })
                scalars.update({f"time/{k}": v / count for k, v in timings.items()})
                network = timings["policy_forward"] + timings["update"]
                scalars["time/non_network_share"] = 1.0 - network / max(sum(timings.values()), 1e-9)
                for key, value in scalars.items():
                    writer.add_scalar(key, value, update)
                totals, count = {}, 0
                interval_start, interval_steps = time.perf_counter(), 0

            do_val = val_env is not None and (
                (val_interval > 0 and update % val_interval == 0) or (val_at_end and update == num_updates)
            )
            if do_val:
                last_val = validate()
                for diff, metrics in last_val.items():
                    for key in ("eps", "omega_stop", "omega_perf", "spl"):
                        writer.add_scalar(f"val/{diff}/{key}", metrics[key], update)
                mean_eps = float(last_val["all"]["eps"])
                if best_val_eps is None or mean_eps < best_val_eps:
                    best_val_eps = mean_eps
                    save_checkpoint(best_path, checkpoint(last_val, with_trainer=False))
                    log.info("new best val eps %.3f at update %d -> %s", mean_eps, update, best_path)
                writer.add_scalar("val/best_eps", best_val_eps, update)
                interval_start = time.perf_counter()  # keep validation out of the fps

            if (ckpt_interval > 0 and update % ckpt_interval == 0) or update == stop_at or do_val:
                save_checkpoint(latest_path, checkpoint(last_val, with_trainer=True))
                last_saved_update = update
        if trainer.update > session_start_update and last_saved_update != trainer.update:
            save_checkpoint(latest_path, checkpoint(last_val, with_trainer=True))  # graceful stop
            last_saved_update = trainer.update
        if trainer.update < num_updates:
            log.info("stopped at update %d of %d; re-run the same command to resume", trainer.update, num_updates)
    finally:
        bar.close()
        writer.close()
        env.close()

    return TrainResult(
        run_dir=run_dir,
        updates=trainer.update,
        env_steps=trainer.env_steps,
        completed=trainer.update >= num_updates,
        latest=latest_path if latest_path.is_file() else None,
        best=best_path if best_path.is_file() else None,
        best_val_eps=best_val_eps,
        last_val=last_val,
        steps_per_second=session_steps / session_time if session_time > 0 else math.nan,
    )


def _bounded_level_setter(source: Any, scheduler: DifficultyScheduler) -> Callable[[int], None]:
    """``scheduler.mode=bounded``: level k samples only the k-th difficulty.

    ``SampledEpisodeSource`` samples ``sampler.sample_level(level)`` (uniform over the first ``level``
    difficulties), so for bounded mode the source's sampler is given a ``sample_level`` that maps level
    k to ``sample(DIFFICULTIES[k-1])``.
    """
    from findview.episode import DIFFICULTIES

    inner = source.sampler

    class _Bounded:
        def __getattr__(self, name: str) -> Any:
            return getattr(inner, name)

        def sample_level(self, level: int) -> Any:
            return inner.sample(DIFFICULTIES[int(level) - 1])

        def state_dict(self) -> dict[str, Any]:
            return inner.state_dict()

        def load_state_dict(self, state: Mapping[str, Any]) -> None:
            inner.load_state_dict(state)

    source.sampler = _Bounded()
    return lambda k: setattr(source, "level", k)
