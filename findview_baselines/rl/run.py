"""A training run (``tools/train.py``): build everything, then :func:`learn` with callbacks for
validation, checkpoints, TensorBoard and the progress bar.

Run folder::

    run_dir/
      .hydra/                 # Hydra's composed config (when started by tools/train.py)
      .run.lock               # held by the live run (pid inside); a second run into the folder is refused
      resolved_config.yaml    # the resolved config of the latest (re)start
      checkpoints/latest.pth  # everything needed to resume exactly
      checkpoints/best.pth    # weights + config + val metrics of the lowest mean val eps so far
      tb/                     # TensorBoard scalars (global step = updates done)

Re-running with the same folder and ``trainer.resume=true`` continues from ``latest.pth``: N updates in
one go and N/2 + resume + N/2 give the same weights (on CPU). SIGTERM / SIGINT stop the run at the next
safe point (the update in flight is abandoned if its rollout is not complete, else finished), write
``latest.pth`` and raise :class:`~findview_baselines.cli.Interrupted` (exit 143 / 130).

Under torchrun (``trainer.distributed=true``, docs/CLUSTER.md) every rank runs this loop on its own
environments and its shard of the train images (rank ``r`` of ``K``: images ``r::K``, seeds ``seed + r``);
the trainers average their gradients over the ranks, :func:`learn` reduces the stats of every update and
makes all ranks agree on a stop (a signal on any rank stops them all at the same safe point). Rank 0
alone holds the lock, validates and writes ``latest.pth`` (with every rank's resume state), ``best.pth``,
TensorBoard and the config; the others wait for it at the next collective. A resume with the same
number of ranks continues exactly; with another number, the weights, optimizer, update count,
schedule and best validation continue, while the environments restart with fresh episodes from
re-seeded RNGs (:func:`findview_baselines.rl.distributed.reseed`).

Validation runs the evaluation harness (:func:`findview_baselines.evaluation.harness.run_episodes`)
with the learned agent wrapper (:class:`~findview_baselines.agents.ppo_agent.PPOAgent`) around the
live policy: the same code path as ``tools/eval.py checkpoint=...``.
"""

from __future__ import annotations

import logging
import math
import os
import random
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from findview.build import build_sampled_env, build_static_env
from findview_baselines.cli import Interrupted, UserError
from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import (
    CHECKPOINT_FORMAT,
    CHECKPOINT_VERSION,
    check_writable,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from findview_baselines.rl.policy import Policy, build_policy
from findview_baselines.rl.ppo_trainer import UpdateAbandoned, no_distribution_validation
from findview_baselines.rl.safety import RunFolderBusy, RunLock, StopOnSignal
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.signature import check_signature

log = logging.getLogger(__name__)

__all__ = [
    "TrainingDiverged",
    "TrainResult",
    "Callback",
    "learn",
    "train",
    "load_policy",
    "select_val_episodes",
    "seed_everything",
]

#: trainer-state entries that are the same on every rank (saved once, by rank 0)
REPLICATED_KEYS = ("signature", "policy", "ppo", "optimizer", "aux_head", "kind")
#: per-rank entries bound to a rank's environments and data; dropped when resuming with another rank count
RANK_DATA_KEYS = ("env", "storage", "current", "episode_returns", "buffer", "rng")

#: per-update stats that set the schedule (logged as their latest value under ``schedule/<key>``)
SCHEDULE_KEYS = ("lr", "clip", "level", "beta", "critic_warmup")
#: per-update stats that are bookkeeping, not metrics (the update index is logged as ``progress/update``)
BOOKKEEPING_KEYS = ("update", "env_steps", "episodes")


def tb_tag(key: str) -> str | None:
    """The TensorBoard tag of a per-update stat a trainer reports: ``loss/<key>`` for losses (``loss`` and
    ``*_loss``), ``schedule/<key>`` for :data:`SCHEDULE_KEYS`, ``update/<key>`` for every other metric
    (``entropy``, ``approx_kl``, ``kl_to_init``, ``oracle_share``, ...); ``None`` for bookkeeping. Every
    numeric stat gets a tag: nothing a trainer reports is dropped."""
    if key in BOOKKEEPING_KEYS:
        return None
    if key in SCHEDULE_KEYS:
        return f"schedule/{key}"
    if key == "loss" or key.endswith("_loss"):
        return f"loss/{key}"
    return f"update/{key}"


class TrainingDiverged(RuntimeError):
    """A non-finite loss / gradient / weight stopped training; the last good checkpoint was kept."""


@dataclass
class TrainResult:
    """What :func:`train` did."""

    run_dir: Path
    updates: int
    """Updates done in total (earlier sessions included)."""
    env_steps: int
    completed: bool
    """Reached trainer.num_updates."""
    latest: Path | None
    best: Path | None
    best_val_eps: float | None
    last_val: dict[str, dict[str, float]] | None
    """``findview.metrics.summarize(..., include_all=True)`` of the last validation."""
    steps_per_second: float
    """Env steps / s of this session's training (validation excluded)."""
    stopped_by: int | None = None
    """The signal that stopped the session, if any."""


# ------------------------------------------------------------------------------------------------
# Small helpers
# ------------------------------------------------------------------------------------------------


def seed_everything(seed: int) -> None:
    """Seed torch (CPU + CUDA), numpy's global RNG and Python's ``random``."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


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


def load_policy(path: str | Path, policy: Policy, transfer: bool = False) -> dict[str, Any]:
    """Load the weights of a checkpoint into ``policy`` after checking its signature; returns the checkpoint.

    ``transfer=True`` (``init_from``) also accepts a checkpoint of a variant with the same parameters
    (``rl/signature.py: TRANSFERABLE_VARIANTS``, e.g. a ``direct`` agent initialising a ``robust`` one).
    Raises ``UserError`` naming the file and the first differing model field.
    """
    state = load_checkpoint(path, map_location=next(policy.parameters()).device)
    try:
        check_signature(state["signature"], policy.model_signature(), transfer=transfer)
    except ValueError as err:
        raise UserError(f"{path}: {err} (use a checkpoint of the same agent.variant / agent.hidden_size / "
                        f"view size, or drop init_from)") from None
    policy.load_state_dict(state["policy"])
    return state


def _plain(cfg: Any) -> dict[str, Any]:
    """A plain, resolved ``dict`` copy of a Hydra / OmegaConf or mapping config."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    return OmegaConf.to_container(OmegaConf.create(dict(cfg)), resolve=True)  # type: ignore[return-value]


def _warn_config_changes(saved: Mapping[str, Any], current: Mapping[str, Any], prefix: str = "") -> None:
    """Log the config values that differ between a checkpoint and the current run (resume keeps going)."""
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            _warn_config_changes(a, b, f"{prefix}{key}.")
        elif a != b and key not in ("resume", "progress", "stop_after"):
            log.warning("resuming with a changed config value %s%s: %r -> %r", prefix, key, a, b)


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


# ------------------------------------------------------------------------------------------------
# The loop and its callbacks
# ------------------------------------------------------------------------------------------------


@dataclass
class RunContext:
    """What the callbacks share: the algorithm, the run's files and its bookkeeping."""

    algo: Any
    conf: dict[str, Any]
    run_dir: Path
    num_updates: int
    best_val_eps: float | None = None
    last_val: dict[str, Any] | None = None
    last_saved_update: int = -1
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def latest_path(self) -> Path:
        return self.run_dir / "checkpoints" / "latest.pth"

    @property
    def best_path(self) -> Path:
        return self.run_dir / "checkpoints" / "best.pth"

    def checkpoint(self, with_trainer: bool) -> dict[str, Any]:
        """The checkpoint payload (``best.pth`` without the trainer's resume state)."""
        policy = self.algo.policy
        return {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "signature": policy.model_signature(),
            "policy": {k: v.detach().cpu() for k, v in policy.state_dict().items()},
            "update": self.algo.update,
            "env_steps": self.algo.env_steps,
            "config": self.conf,
            "val": self.last_val,
            "best_val_eps": self.best_val_eps,
            "trainer": self.algo.state_dict() if with_trainer else None,
        }

    def save_latest(self) -> None:
        """Write ``latest.pth``. Under torchrun a collective: every rank sends its own resume state
        (environments, RNGs, storage) to rank 0, which writes them all (``trainer["rank_states"]``)."""
        if distributed.world_size() == 1:
            save_checkpoint(self.latest_path, self.checkpoint(with_trainer=True))
        else:
            own = None if distributed.is_main() else {
                k: v for k, v in self.algo.state_dict().items() if k not in REPLICATED_KEYS}
            parts = distributed.gather_to_main(own)
            if parts is not None:
                state = self.checkpoint(with_trainer=True)
                state["trainer"] = {**state["trainer"], "world_size": len(parts), "rank_states": parts[1:]}
                save_checkpoint(self.latest_path, state)
        self.last_saved_update = self.algo.update


class Callback:
    """Hooks of :func:`learn`; override what you need."""

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        """After every completed update (``ctx.algo.update`` already counts it)."""

    def on_end(self, ctx: RunContext, stopped: bool) -> None:
        """After the last update of this session (``stopped``: a signal ended it early)."""


def learn(ctx: RunContext, callbacks: Sequence[Callback], stop_at: int, stop: StopOnSignal) -> None:
    """Run updates until ``stop_at`` updates are done or a stop is requested; callbacks do the rest.

    ``stop`` is a :class:`StopOnSignal`, or under torchrun an :class:`~findview_baselines.rl.distributed.AgreedStop`
    (every rank stops at the same point); the stats of every update are reduced over the ranks before the
    callbacks see them."""
    algo = ctx.algo
    try:
        stopping = stop.agree()
        while algo.update < stop_at and not stopping:
            try:
                stats = algo.train_update(stop)
            except UpdateAbandoned as err:
                log.info("%s", err)
                stop.agree()  # every rank learns the signal (with preemption, some only saw it abandon)
                break
            except FloatingPointError as err:
                kept = (
                    f"the last good checkpoint {ctx.latest_path} (update {ctx.last_saved_update}) was kept"
                    if ctx.latest_path.is_file() and ctx.last_saved_update >= 0
                    else "no checkpoint had been written yet"
                )
                raise TrainingDiverged(
                    f"training diverged at update {algo.update + 1}: {err}; {kept}. Lower the learning rate or "
                    f"check the inputs, then re-run to resume from the last checkpoint."
                ) from err
            stats = distributed.reduce_stats(stats)
            # a stop asked for during this update (agreed by every rank): the callbacks skip what can wait
            # (a scheduled validation) and the session ends after them, writing latest.pth
            stopping = stop.agree()
            ctx.extra["stopping"] = stopping
            for cb in callbacks:
                cb.on_update(ctx, stats)
    except BaseException:
        ctx.extra["failed"] = True  # under torchrun: no more collectives (the other ranks may be gone)
        raise
    finally:
        if not ctx.extra.get("failed"):
            stop.close()
        for cb in callbacks:
            cb.on_end(ctx, stop.requested)


class ProgressCallback(Callback):
    """tqdm bar over updates with recent training metrics."""

    def __init__(self, total: int, initial: int, enabled: bool, steps_per_update: int) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, initial=initial, unit="upd", dynamic_ncols=True, disable=not enabled)
        self.steps_per_update = steps_per_update
        self.window = _MetricWindow(size=200)
        self.t_last = time.perf_counter()

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        now = time.perf_counter()
        dt, self.t_last = now - self.t_last, now
        self.window.add(stats.get("episodes", []))
        recent = self.window.summary()
        self.bar.update(1)
        self.bar.set_postfix(
            sps=f"{self.steps_per_update / max(dt, 1e-9):.0f}", lvl=stats.get("level"),
            eps=f"{recent.get('eps', float('nan')):.1f}", succ=f"{recent.get('success_rate', float('nan')):.2f}",
            refresh=False,
        )

    def on_end(self, ctx: RunContext, stopped: bool) -> None:
        self.bar.close()


class TensorBoardCallback(Callback):
    """Scalars every ``log_interval`` updates against the env steps so far (the x-axis habitat-baselines
    and SB3 runs are compared by): every numeric stat of the updates (:func:`tb_tag`; metrics averaged
    over the interval, schedule values as of the last update), the update index (``progress/update``),
    recent episodes, speed and phase timings."""

    def __init__(self, run_dir: Path, log_interval: int, resumed_at: int, steps_per_update: int) -> None:
        """``resumed_at``: the env steps a resumed session starts from (-1 for a fresh run)."""
        from torch.utils.tensorboard import SummaryWriter

        # purge_step drops events a crashed session logged after the checkpoint it is resumed from
        self.writer = SummaryWriter(log_dir=str(run_dir / "tb"), purge_step=resumed_at + 1)
        self.log_interval = max(1, log_interval)
        self.steps_per_update = steps_per_update
        self.window = _MetricWindow(size=200)
        self.totals: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.count = 0
        self.t0 = time.perf_counter()
        self.steps = 0

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        self.window.add(stats.get("episodes", []))
        for key, value in stats.items():
            tag = tb_tag(key)
            if tag is None or not isinstance(value, (int, float)) or tag.startswith("schedule/"):
                continue
            self.totals[tag] = self.totals.get(tag, 0.0) + float(value)
            self.counts[tag] = self.counts.get(tag, 0) + 1
        self.count += 1
        self.steps += self.steps_per_update
        update = ctx.algo.update
        if update % self.log_interval and update != ctx.extra.get("stop_at"):
            return
        elapsed = time.perf_counter() - self.t0
        timings = ctx.algo.pop_timings()
        scalars = {tag: v / self.counts[tag] for tag, v in self.totals.items()}
        scalars.update({f"train/{k}": v for k, v in self.window.summary().items()})
        for key in SCHEDULE_KEYS:
            if isinstance(stats.get(key), (int, float)):
                scalars[f"schedule/{key}"] = float(stats[key])
        scalars["progress/update"] = float(update)
        scalars["perf/fps"] = self.steps / max(elapsed, 1e-9)
        scalars["perf/env_steps"] = float(ctx.algo.env_steps)
        scalars.update({f"time/{k}": v / self.count for k, v in timings.items()})
        for key, value in scalars.items():
            self.writer.add_scalar(key, value, ctx.algo.env_steps)
        self.totals, self.counts, self.count, self.steps, self.t0 = {}, {}, 0, 0, time.perf_counter()

    def add_validation(self, env_steps: int, result: Mapping[str, Mapping[str, float]], best: float) -> None:
        """The validation metrics at ``env_steps`` (the x-axis of every scalar)."""
        for diff, metrics in result.items():
            for key in ("eps", "omega_stop", "omega_perf", "spl"):
                self.writer.add_scalar(f"val/{diff}/{key}", metrics[key], env_steps)
        self.writer.add_scalar("val/best_eps", best, env_steps)
        self.t0 = time.perf_counter()  # keep validation out of the fps

    def on_end(self, ctx: RunContext, stopped: bool) -> None:
        self.writer.close()


class ValidationCallback(Callback):
    """Every ``interval`` updates (and after the last one): play the val episodes with the learned-agent
    wrapper through the evaluation harness; keep ``best.pth`` (lowest mean val eps)."""

    def __init__(self, val_env: Any, agent: Any, interval: int, at_end: bool, tb: TensorBoardCallback | None) -> None:
        self.env, self.agent = val_env, agent
        self.interval, self.at_end, self.tb = interval, at_end, tb

    def validate(self, ctx: RunContext) -> dict[str, Any]:
        """Play the val episodes (rank 0 only: the other ranks have no val environment)."""
        from findview.metrics import summarize
        from findview_baselines.evaluation.harness import run_episodes

        self.env.source.load_state_dict({"index": 0})
        start = time.perf_counter()
        records, _ = run_episodes(self.env, self.agent, progress=False)
        result = summarize(records, include_all=True)
        log.info(
            "val at update %d (%d episodes, %.1fs): %s", ctx.algo.update, len(records), time.perf_counter() - start,
            ", ".join(f"{d} eps {m['eps']:.2f} stop {m['omega_stop']:.2f} spl {m['spl']:.2f}" for d, m in result.items()),
        )
        return result

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        update = ctx.algo.update
        due = (self.interval > 0 and update % self.interval == 0) or (self.at_end and update == ctx.num_updates)
        if not due:
            return
        if ctx.extra.get("stopping"):  # a signal asked to stop: write latest.pth now, validate another time
            if self.env is not None:
                log.info("stop requested: validation at update %d skipped", update)
            return
        ctx.extra["validated_at"] = update  # on every rank: the checkpoint that follows is collective
        if self.env is None:
            return  # not rank 0
        ctx.last_val = self.validate(ctx)
        mean_eps = float(ctx.last_val["all"]["eps"])
        if ctx.best_val_eps is None or mean_eps < ctx.best_val_eps:
            ctx.best_val_eps = mean_eps
            save_checkpoint(ctx.best_path, ctx.checkpoint(with_trainer=False))
            log.info("new best val eps %.3f at update %d -> %s", mean_eps, update, ctx.best_path)
        if self.tb is not None:
            self.tb.add_validation(ctx.algo.env_steps, ctx.last_val, ctx.best_val_eps)


class CheckpointCallback(Callback):
    """``latest.pth`` every ``interval`` updates, after every validation and when the session ends."""

    def __init__(self, interval: int) -> None:
        self.interval = interval

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        update = ctx.algo.update
        if (self.interval > 0 and update % self.interval == 0) or ctx.extra.get("validated_at") == update \
                or update == ctx.extra.get("stop_at"):
            ctx.save_latest()

    def on_end(self, ctx: RunContext, stopped: bool) -> None:
        if ctx.extra.get("failed") and distributed.world_size() > 1:
            return  # a collective save could wait forever for a rank that failed; the last periodic one stays
        started = ctx.extra.get("session_start_update", 0)
        if (ctx.algo.update > started or stopped) and ctx.last_saved_update != ctx.algo.update:
            ctx.save_latest()


class SeverityRamp(Callback):
    """``corruption.ramp_updates > 0``: the highest target-corruption severity of new training episodes
    rises linearly from ``low`` to ``high`` over that many updates (fine-tuning with corruptions as
    augmentation; validation keeps the full range)."""

    def __init__(self, transform: Any, ramp_updates: int) -> None:
        self.transform, self.ramp_updates = transform, max(1, int(ramp_updates))

    def set_for(self, update: int) -> None:
        low, high = self.transform.low, self.transform.high
        self.transform.max_severity = low + int((high - low) * min(1.0, update / self.ramp_updates))

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        self.set_for(ctx.algo.update)


# ------------------------------------------------------------------------------------------------
# Building a run
# ------------------------------------------------------------------------------------------------


def _build_data(conf: Mapping[str, Any], dataset_cfg: Any, progress: bool) -> tuple[list[Any], list[Any]]:
    """(train images, val episodes) of the configured dataset; makes the dataset files if missing."""
    from findview.dataset import dataset_settings, ensure_dataset, episode_file, load_episodes, load_split

    fov = float(conf["sim"]["fov"])
    task = conf["task"]
    out_dir = ensure_dataset(dataset_cfg, [fov], pitch_bound=int(task["pitch_bound"]), progress=progress, log=log.info)
    train_images = load_split(out_dir, "train")
    if not train_images:
        raise UserError(f"the train split of dataset {conf['dataset'].get('name')!r} in {out_dir} is empty")
    path = episode_file(out_dir, "val", fov)
    k = dataset_settings(dataset_cfg)["episodes_per_image"]  # a file made with more serves its first k per image
    val_episodes = load_episodes(path, episodes_per_image=k) if path.is_file() else []
    return train_images, val_episodes


def make_algorithm(conf: Mapping[str, Any], env: Any, policy: Policy, scheduler: DifficultyScheduler, source: Any,
                   seed: int | None = None) -> Any:
    """The algorithm of ``trainer.algorithm`` (``ppo`` | ``dagger``) around ``env`` and ``policy``.

    ``seed``: seeds the algorithm's own generators (default ``trainer.seed``; rank ``r`` passes its own)."""
    t, agent = conf["trainer"], conf["agent"]
    seed = int(t["seed"]) if seed is None else int(seed)
    set_level = lambda k: setattr(source, "level", k)  # noqa: E731
    if t.get("algorithm", "ppo") == "dagger":
        from findview_baselines.agents.revisit import search_settings
        from findview_baselines.rl.dagger import DAggerConfig, DAggerTrainer

        dcfg = DAggerConfig.from_mapping(dict(t.get("dagger") or {}))
        return DAggerTrainer(env, policy, dcfg, int(t["num_updates"]), scheduler, set_level, seed=seed,
                             **search_settings(agent))
    from findview_baselines.rl.ppo import PPOConfig
    from findview_baselines.rl.ppo_trainer import PPOTrainer

    ppo_cfg = PPOConfig.from_mapping(agent)
    return PPOTrainer(env, policy, ppo_cfg, int(t["num_updates"]), scheduler, set_level, seed=seed)


def train(cfg: Any, run_dir: str | Path, progress: bool | None = None) -> TrainResult:
    """Train (or resume) the learned agent described by ``cfg`` (the ``configs/train.yaml`` tree) in ``run_dir``.

    With ``trainer.distributed=true`` this process is one rank of a torchrun job (see the module docstring);
    it joins the job first and leaves it at the end.

    Raises:
        UserError / PermissionError / ValueError: a bad value, an unwritable folder, a run folder held by a
            live run, or a checkpoint that does not fit (naming the file and the way out).
        TrainingDiverged: a non-finite loss / weight; ``latest.pth`` keeps the last good state.
        Interrupted: SIGTERM / SIGINT / SIGUSR1 stopped the run after writing ``latest.pth`` (under torchrun:
            a signal to any rank; every rank raises it, with the same signal).
    """
    t = cfg["trainer"]
    joined = False
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if not bool(t.get("distributed", False)) and world > 1 and distributed.launched_by_torchrun():
        raise UserError(f"started by torchrun with {world} processes but trainer.distributed=false: add "
                        f"trainer.distributed=true (or run one process)")
    if bool(t.get("distributed", False)) and not distributed.is_active():
        from findview.sim import resolve_device

        device = resolve_device(str(cfg["sim"].get("device") or "auto"))
        distributed.setup(str(t.get("dist_backend") or "auto"), device, float(t.get("dist_timeout_min") or 60))
        joined = True
    try:
        return _train_joined(cfg, run_dir, progress)
    finally:
        if joined:
            distributed.teardown()


def _take_lock(run_dir: Path) -> RunLock | None:
    """Rank 0 locks the run folder; every rank learns whether that worked (UserError everywhere if not)."""
    lock, error = None, None
    if distributed.is_main():
        try:
            lock = RunLock(run_dir).__enter__()
        except RunFolderBusy as err:
            error = str(err)
    error = distributed.all_gather(error)[0]
    if error is not None:
        raise UserError(error)
    return lock


def _train_joined(cfg: Any, run_dir: str | Path, progress: bool | None) -> TrainResult:
    run_dir = check_writable(run_dir, "run folder")
    check_writable(run_dir / "checkpoints", "checkpoint folder")
    lock = _take_lock(run_dir)
    try:
        with no_distribution_validation(), StopOnSignal() as signals:
            stop: Any = signals
            if distributed.is_active():
                stop = distributed.AgreedStop(signals, preemption=_preemption(cfg["trainer"]))
            result = _train_locked(cfg, run_dir, stop, progress)
            if result.stopped_by is not None and distributed.world_size() > 1:
                signals.ignore_after_exit()  # all saved; torchrun's SIGTERM to the last ranks must not kill them
    finally:
        if lock is not None:
            lock.__exit__(None, None, None)
    if result.stopped_by is not None:
        import signal as _signal

        name = _signal.Signals(result.stopped_by).name
        raise Interrupted(
            result.stopped_by,
            f"{name}: stopped at update {result.updates}; resume state written to {result.latest}. "
            f"Re-run the same command to resume.",
        )
    return result


def _preemption(t: Any) -> distributed.Preemption | None:
    """Straggler preemption of ``trainer.preempt_fraction`` (> 0, PPO, several ranks), else ``None``."""
    fraction = float(t.get("preempt_fraction") or 0.0)
    if fraction <= 0 or distributed.world_size() == 1:
        return None
    if str(t.get("algorithm", "ppo")) != "ppo":
        raise UserError(f"trainer.preempt_fraction={fraction} works with trainer.algorithm=ppo only, not "
                        f"{t.get('algorithm')!r}; set trainer.preempt_fraction=0")
    return distributed.Preemption(fraction)


def _rank_trainer_state(trainer: Mapping[str, Any], rank: int, world: int, seed: int) -> tuple[dict[str, Any], bool]:
    """This rank's trainer state from ``latest.pth``'s ``trainer`` entry, and whether it continues exactly.

    Same number of ranks as saved: rank 0's state with rank ``rank``'s own entries on top (exact). Another
    number: rank 0's state without the environment-bound entries (:data:`RANK_DATA_KEYS`) and with every
    generator state (``*_rng``) re-seeded from :func:`distributed.reseed`; the caller restarts the
    environments."""
    saved_world = int(trainer.get("world_size", 1))
    state = {k: v for k, v in trainer.items() if k not in ("world_size", "rank_states")}
    if saved_world == world:
        if rank > 0:
            state.update(trainer["rank_states"][rank - 1])
        return state, True
    update = int(trainer["update"])
    for key in RANK_DATA_KEYS:
        state[key] = None
    generators = sorted(key for key in state if key.endswith("_rng"))
    for i, key in enumerate(generators):
        state[key] = torch.Generator().manual_seed(distributed.reseed(seed, rank, update) + i + 1).get_state()
    return state, False


def _train_locked(cfg: Any, run_dir: Path, stop: Any, progress: bool | None) -> TrainResult:
    from findview.dataset import EpisodeSampler
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.agents.revisit import search_settings

    conf = _plain(cfg)
    dataset_cfg = cfg["dataset"]
    t, sim_cfg, task_cfg, agent_cfg = conf["trainer"], conf["sim"], conf["task"], conf["agent"]
    num_updates, num_envs, seed = int(t["num_updates"]), int(t["num_envs"]), int(t["seed"])
    rank, world, main = distributed.rank(), distributed.world_size(), distributed.is_main()
    show_progress = (bool(t.get("progress", True)) if progress is None else progress) and main
    latest_path = run_dir / "checkpoints" / "latest.pth"
    if distributed.is_active():
        from findview.sim import resolve_device

        device = resolve_device(str(sim_cfg.get("device") or "auto"))
        if device.type == "cuda":  # one GPU per rank
            sim_cfg = {**sim_cfg, "device": f"cuda:{distributed.local_rank()}"}

    resume_state: dict[str, Any] | None = None
    if bool(t.get("resume", True)) and latest_path.is_file():
        try:
            resume_state = load_checkpoint(latest_path)
        except ValueError as err:
            raise UserError(f"{err}; move it away or start over with trainer.resume=false") from None
        if resume_state.get("trainer") is None:
            raise UserError(f"{latest_path} holds no trainer state; start over with trainer.resume=false")
        if main:
            _warn_config_changes(resume_state.get("config") or {}, conf)
    elif latest_path.is_file() and main:
        log.warning("trainer.resume=false: starting over in %s (the old latest.pth will be overwritten)", run_dir)
    if world > 1:
        seen = distributed.all_gather(None if resume_state is None else int(resume_state["update"]))
        if len(set(seen)) > 1:
            raise UserError(f"the ranks see different resume states in {latest_path} (updates {seen} by rank): the "
                            f"run folder must be on a file system every machine shares")

    rank_state, exact = None, True
    if resume_state is not None:
        rank_state, exact = _rank_trainer_state(resume_state["trainer"], rank, world, seed)
    # rank r: seed + r (rank 0 / a single process: trainer.seed); a resume with another rank count re-seeds
    rank_seed = seed + rank
    if resume_state is not None and not exact:
        rank_seed = distributed.reseed(seed, rank, int(resume_state["update"]))
    seed_everything(rank_seed)
    train_images, val_all = distributed.main_first(lambda: _build_data(conf, dataset_cfg, show_progress))
    train_images = distributed.shard(train_images, rank, world)
    need_val = bool(t.get("val_at_end", True)) or int(t.get("val_interval", 0)) > 0
    val_episodes = select_val_episodes(val_all, t.get("val_episodes")) if need_val and main else []
    if need_val and main and not val_episodes:
        log.warning("no val episodes: validation and best.pth are skipped")

    sched_cfg = conf.get("scheduler") or {}
    scheduler = DifficultyScheduler(num_updates, num_levels=int(sched_cfg.get("num_levels", 3)),
                                    mode=str(sched_cfg.get("mode", "unbounded")),
                                    start_level=int(sched_cfg.get("start_level", 1)))
    sampler = EpisodeSampler(
        train_images, float(sim_cfg["fov"]), seed=rank_seed, pitch_bound=int(task_cfg["pitch_bound"]),
        max_steps=int(task_cfg["max_steps"]), hard_rule=str(conf["dataset"].get("hard_rule", "or")),
    )
    val_envs = min(int(t.get("val_num_envs") or num_envs), len(val_episodes)) if val_episodes else 0
    env = build_sampled_env(
        sim_cfg, task_cfg, sampler, num_envs, mode=scheduler.mode, corruption_cfg=conf.get("corruption"),
        extra_images=[e.image for e in val_episodes], extra_slots=val_envs,
    )
    device = env.device
    val_env = (
        build_static_env(sim_cfg, task_cfg, val_episodes, val_envs, corruption_cfg=conf.get("corruption"),
                         max_steps=t.get("val_max_steps"), simulator=env.sim)
        if val_episodes else None
    )
    policy = build_policy(agent_cfg, int(sim_cfg["height"]), int(sim_cfg["width"])).to(device)
    algo = make_algorithm(conf, env, policy, scheduler, env.source, seed=rank_seed)
    if getattr(stop, "preemption", None) is not None:
        algo.preemption = stop.preemption
    # the same initial weights everywhere (each rank seeded its own RNGs): rank 0's, incl. an auxiliary head
    aux_heads = [getattr(algo, "aux_head", None), getattr(getattr(algo, "ppo", None), "aux_head", None)]
    distributed.broadcast_modules([policy, *aux_heads])
    ctx = RunContext(algo, conf, run_dir, num_updates)
    ramp = None
    if env.target_transform is not None and int((conf.get("corruption") or {}).get("ramp_updates", 0)) > 0:
        ramp = SeverityRamp(env.target_transform, int(conf["corruption"]["ramp_updates"]))
        ramp.set_for(int(resume_state["update"]) if resume_state is not None else 0)  # before any target is made

    if resume_state is not None:
        try:
            algo.load_state_dict(rank_state, restore_rng=False)
        except (ValueError, KeyError, RuntimeError) as err:
            raise UserError(f"{latest_path} does not fit this run ({err}); start over with trainer.resume=false "
                            f"or train into another folder") from None
        if not exact:
            algo.start()  # fresh episodes on this rank's new shard
        ctx.best_val_eps = resume_state.get("best_val_eps")
        ctx.last_val = resume_state.get("val")
        ctx.last_saved_update = algo.update
        saved_world = int(resume_state["trainer"].get("world_size", 1))
        log.info("resumed %s at update %d (%d env steps)%s", run_dir, algo.update, algo.env_steps,
                 "" if exact else f"; saved by {saved_world} rank(s), now {world}: weights, optimizer and schedule "
                                  f"continue, environments restart with re-seeded episodes")
    else:
        if conf.get("init_from"):
            state = load_policy(Path(str(conf["init_from"])).expanduser(), policy, transfer=True)
            log.info("initialised the weights from %s (update %s of that run); fresh optimizer",
                     conf["init_from"], state.get("update"))
        algo.start()

    from omegaconf import OmegaConf

    from findview.utils import write_text

    if main:
        write_text(run_dir / "resolved_config.yaml", OmegaConf.to_yaml(OmegaConf.create(conf)))
    if resume_state is not None:
        if exact:
            assert rank_state is not None
            restore_rng_state(rank_state["rng"])  # last: building the run consumed random numbers
        else:
            seed_everything(rank_seed)

    stop_after = t.get("stop_after")
    stop_at = num_updates if stop_after is None else min(num_updates, algo.update + int(stop_after))
    ctx.extra.update(stop_at=stop_at, session_start_update=algo.update)
    if algo.update >= num_updates and main:
        log.info("run %s is already complete (%d updates); nothing to do", run_dir, algo.update)
    steps_per_update = int(getattr(algo.cfg, "rollout_steps", 1)) * num_envs * world  # all ranks
    callbacks: list[Callback] = []
    tb = None
    if main:
        tb = TensorBoardCallback(run_dir, int(t.get("log_interval", 10)),
                                 algo.env_steps if resume_state is not None else -1, steps_per_update)
        callbacks += [ProgressCallback(num_updates, algo.update, show_progress, steps_per_update), tb]
    main_validates = distributed.all_gather(val_env is not None)[0]  # only rank 0 has val episodes
    if val_env is not None:
        agent = PPOAgent(policy, val_envs, device, seed, sample=bool(agent_cfg.get("sample", False)),
                         **search_settings(agent_cfg))
        callbacks.append(ValidationCallback(val_env, agent, int(t.get("val_interval", 0)),
                                            bool(t.get("val_at_end", True)), tb))
    elif main_validates:
        # not rank 0: keeps rank 0's validation schedule (and the collective checkpoints after it) in step
        callbacks.append(ValidationCallback(None, None, int(t.get("val_interval", 0)), bool(t.get("val_at_end", True)),
                                            None))
    callbacks.append(CheckpointCallback(int(t.get("checkpoint_interval", 100))))
    if ramp is not None:
        callbacks.insert(0, ramp)

    session_start, t_start = algo.update, time.perf_counter()
    try:
        learn(ctx, callbacks, stop_at, stop)
        distributed.barrier()  # nobody leaves before rank 0 has written its files
    finally:
        env.close()
    session_time = time.perf_counter() - t_start
    if algo.update < num_updates and not stop.requested and main:
        log.info("stopped at update %d of %d; re-run the same command to resume", algo.update, num_updates)
    return TrainResult(
        run_dir=run_dir,
        updates=algo.update,
        env_steps=algo.env_steps,
        completed=algo.update >= num_updates,
        latest=latest_path if latest_path.is_file() else None,
        best=ctx.best_path if ctx.best_path.is_file() else None,
        best_val_eps=ctx.best_val_eps,
        last_val=ctx.last_val,
        steps_per_second=(algo.update - session_start) * steps_per_update / session_time if session_time > 0 else math.nan,
        stopped_by=stop.signum,
    )
