"""A training run (``tools/train.py``): :func:`train` builds everything (:mod:`.build`), resumes
(:mod:`.resume`), then runs :func:`~findview_baselines.training.loop.learn` with the callbacks of
:mod:`.callbacks` (validation, checkpoints, TensorBoard, the progress bar).

Run folder::

    run_dir/
      .hydra/                 # Hydra's composed config (when started by tools/train.py)
      .run.lock               # held by the live run (pid inside); a second run into the folder is refused
      resolved_config.yaml    # the resolved config of the latest (re)start
      checkpoints/latest.pth  # everything needed to resume exactly
      checkpoints/best.pth    # weights + config + val metrics of the lowest mean val eps so far
      tb/                     # TensorBoard scalars (x-axis: env steps)

Re-running with the same folder and ``trainer.resume=true`` continues from ``latest.pth``: N updates in
one go and N/2 + resume + N/2 give the same weights (on CPU). SIGTERM / SIGINT stop the run at the next
safe point (the update in flight is abandoned if its rollout is not complete, else finished), write
``latest.pth`` and raise :class:`~findview_baselines.errors.Interrupted` (exit 143 / 130).

Under torchrun (``trainer.distributed=true``, docs/CLUSTER.md) every rank runs this loop on its own
environments and its shard of the train images (rank ``r`` of ``K``: images ``r::K``, seeds ``seed + r``);
the trainers average their gradients over the ranks, :func:`learn` reduces the stats of every update and
makes all ranks agree on a stop (a signal on any rank stops them all at the same safe point). Rank 0
alone holds the lock, validates and writes ``latest.pth`` (with every rank's resume state), ``best.pth``,
TensorBoard and the config; the others wait for it at the next collective. A resume with the same
number of ranks continues exactly; with another number, the weights, optimizer, update count,
schedule and best validation continue, while the environments restart with fresh episodes from
re-seeded RNGs (:func:`findview_baselines.rl.distributed.reseed`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import signal as signal_module
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from findview_baselines.config import TrainConfig, typed_config
from findview_baselines.errors import Interrupted, UserError
from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import check_writable, load_policy, restore_rng_state
from findview_baselines.rl.safety import RunFolderBusy, RunLock, StopOnSignal
from findview_baselines.rl.trainer_base import Trainer, no_distribution_validation
from findview_baselines.training.build import build_run, make_val_agent, seed_everything
from findview_baselines.training.callbacks import (
    Callback,
    CheckpointCallback,
    ProgressCallback,
    SeverityRamp,
    TensorBoardCallback,
    ValidationCallback,
)
from findview_baselines.training.loop import RunContext, TrainingDiverged, learn
from findview_baselines.training.resume import rank_trainer_state, read_resume_state

log = logging.getLogger(__name__)

__all__ = ["TrainResult", "TrainingDiverged", "train"]


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
    """Env steps / s of this session: its env steps over its wall time, validations and checkpoints included."""
    stopped_by: int | None = None
    """The signal that stopped the session, if any."""


def train(cfg: Any, run_dir: str | Path, progress: bool | None = None) -> TrainResult:
    """Train (or resume) the learned agent described by ``cfg`` in ``run_dir``.

    ``cfg``: the validated :class:`~findview_baselines.config.TrainConfig` (a composed ``configs/train.yaml``
    ``DictConfig`` is validated first). With ``trainer.distributed=true`` this process is one rank of a
    torchrun job (see the module docstring); it joins the job first and leaves it at the end.

    Threads: ``trainer.torch_threads`` is applied by ``tools/train.py`` (:func:`findview.runtime.configure_threads`,
    for the whole process); called in process, ``train`` runs on the caller's thread count, and the trained weights
    depend on it (floating-point sums split across threads): call ``configure_threads`` first to reproduce a CLI run.

    Raises:
        UserError / ConfigError / CheckpointError / OutputPathError: a bad value, an unwritable folder, a run
            folder held by a live run, or a checkpoint that does not fit (naming the file and the way out).
        TrainingDiverged: a non-finite loss / weight; ``latest.pth`` keeps the last good state.
        Interrupted: SIGTERM / SIGINT / SIGUSR1 stopped the run after writing ``latest.pth`` (under torchrun:
            a signal to any rank; every rank raises it, with the same signal).
    """
    cfg = typed_config(cfg)
    t = cfg.trainer
    world = int(os.environ.get("WORLD_SIZE", "1") or 1)
    if not t.distributed and world > 1 and distributed.launched_by_torchrun():
        raise UserError(f"started by torchrun with {world} processes but trainer.distributed=false: add "
                        f"trainer.distributed=true (or run one process)")
    joined = False
    if t.distributed and not distributed.is_active():
        from findview.sim import resolve_device

        distributed.setup(t.dist_backend, resolve_device(cfg.sim.device), t.dist_timeout_min)
        joined = True
    try:
        return _train_joined(cfg, Path(run_dir), progress)
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


def _preemption(cfg: TrainConfig) -> distributed.Preemption | None:
    """Straggler preemption of ``trainer.preempt_fraction`` (> 0, PPO, several ranks), else ``None``."""
    fraction = cfg.trainer.preempt_fraction
    if fraction <= 0 or distributed.world_size() == 1:
        return None
    if cfg.trainer.algorithm != "ppo":
        raise UserError(f"trainer.preempt_fraction={fraction} works with trainer.algorithm=ppo only, not "
                        f"{cfg.trainer.algorithm!r}; set trainer.preempt_fraction=0")
    return distributed.Preemption(fraction)


def _train_joined(cfg: TrainConfig, run_dir: Path, progress: bool | None) -> TrainResult:
    run_dir = check_writable(run_dir, "run folder")
    check_writable(run_dir / "checkpoints", "checkpoint folder")
    lock = _take_lock(run_dir)
    try:
        with no_distribution_validation(), StopOnSignal() as signals:
            stop: Any = signals
            if distributed.is_active():
                stop = distributed.AgreedStop(signals, preemption=_preemption(cfg))
            result = _train_locked(cfg, run_dir, stop, progress)
            if result.stopped_by is not None and distributed.world_size() > 1:
                signals.ignore_after_exit()  # all saved; torchrun's SIGTERM to the last ranks must not kill them
    finally:
        if lock is not None:
            lock.__exit__(None, None, None)
    if result.stopped_by is not None:
        name = signal_module.Signals(result.stopped_by).name
        raise Interrupted(result.stopped_by, f"{name}: stopped at update {result.updates}; resume state written to "
                                             f"{result.latest}. Re-run the same command to resume.")
    return result


def config_dict(cfg: TrainConfig) -> dict[str, Any]:
    """The run's config as a plain dict (stored in every checkpoint and in ``resolved_config.yaml``)."""
    return dataclasses.asdict(cfg)


def _start(ctx: RunContext, cfg: TrainConfig, resume_state: dict[str, Any] | None, rank_seed: int) -> Callable[[], None]:
    """Put the trainer where this session starts: a resumed state (exact or re-sharded), or fresh weights
    (``init_from``) and fresh episodes. Returns what sets the global RNGs once everything is built (building
    consumes random numbers): the saved states of an exact resume, a re-seed of a re-sharded one."""
    algo, latest = ctx.algo, ctx.latest_path
    if resume_state is None:
        if cfg.init_from:
            state = load_policy(Path(cfg.init_from).expanduser(), algo.policy, transfer=True, key="init_from")
            log.info("initialised the weights from %s (update %s of that run); fresh optimizer",
                     cfg.init_from, state["update"])
        algo.start()
        return lambda: None
    world = distributed.world_size()
    rank_state, exact = rank_trainer_state(resume_state["trainer"], distributed.rank(), world, cfg.trainer.seed)
    try:
        algo.load_state_dict(rank_state, restore_rng=False)
    except (ValueError, KeyError, RuntimeError) as err:
        raise UserError(f"{latest} does not fit this run ({err}); start over with trainer.resume=false "
                        f"or train into another folder") from None
    if not exact:
        algo.start()  # fresh episodes on this rank's new shard
    ctx.best_val_eps, ctx.last_val = resume_state["best_val_eps"], resume_state["val"]
    ctx.last_saved_update = algo.update
    saved_world = int(resume_state["trainer"].get("world_size", 1))  # absent in single-process checkpoints
    log.info("resumed %s at update %d (%d env steps)%s", ctx.run_dir, algo.update, algo.env_steps,
             "" if exact else f"; saved by {saved_world} rank(s), now {world}: weights, optimizer and schedule "
                              f"continue, environments restart with re-seeded episodes")
    rng = rank_state["rng"]
    return (lambda: restore_rng_state(rng)) if exact else (lambda: seed_everything(rank_seed))


def _callbacks(ctx: RunContext, cfg: TrainConfig, val_env: Any, show_progress: bool, resumed: bool) -> list[Callback]:
    """Progress, TensorBoard (rank 0), validation (rank 0 plays; the others keep its schedule), checkpoints."""
    t, algo = cfg.trainer, ctx.algo
    steps_per_update = algo.steps_per_update * distributed.world_size()  # all ranks
    callbacks: list[Callback] = []
    tb = None
    if distributed.is_main():
        tb = TensorBoardCallback(ctx.run_dir, t.log_interval, algo.env_steps if resumed else -1, steps_per_update)
        callbacks += [ProgressCallback(t.num_updates, algo.update, show_progress, steps_per_update), tb]
    main_validates = distributed.all_gather(val_env is not None)[0]  # only rank 0 has val episodes
    if val_env is not None:
        agent = make_val_agent(cfg.agent, algo.policy, val_env.num_envs, t.seed)
        callbacks.append(ValidationCallback(val_env, agent, t.val_interval, t.val_at_end, tb, t.keep_val_checkpoints))
    elif main_validates:
        callbacks.append(ValidationCallback(None, None, t.val_interval, t.val_at_end, None))
    callbacks.append(CheckpointCallback(t.checkpoint_interval))
    return callbacks


def _severity_ramp(cfg: TrainConfig, env: Any, start_update: int) -> SeverityRamp | None:
    """The ``corruption.ramp_updates`` callback, set for the first update before any target is made."""
    if env.target_transform is None or cfg.corruption.ramp_updates <= 0:
        return None
    ramp = SeverityRamp(env.target_transform, cfg.corruption.ramp_updates)
    ramp.set_for(start_update)
    return ramp


def _train_locked(cfg: TrainConfig, run_dir: Path, stop: Any, progress: bool | None) -> TrainResult:
    from omegaconf import OmegaConf

    from findview.utils import write_text

    t, main, rank = cfg.trainer, distributed.is_main(), distributed.rank()
    config = config_dict(cfg)
    show_progress = (t.progress if progress is None else progress) and main
    resume_state = read_resume_state(run_dir / "checkpoints" / "latest.pth", t.resume, config)
    # rank r: seed + r (rank 0 / a single process: trainer.seed); a resume with another rank count re-seeds
    rank_seed = t.seed + rank
    if resume_state is not None and int(resume_state["trainer"].get("world_size", 1)) != distributed.world_size():
        rank_seed = distributed.reseed(t.seed, rank, int(resume_state["update"]))
    seed_everything(rank_seed)
    parts = build_run(cfg, rank_seed, show_progress)
    algo: Trainer = parts.trainer
    if isinstance(stop, distributed.AgreedStop) and stop.preemption is not None:
        if not algo.supports_preemption:
            raise UserError(f"trainer.preempt_fraction works with trainer.algorithm=ppo only, not {t.algorithm!r}")
        algo.preemption = stop.preemption
    # the same initial weights everywhere (each rank seeded its own RNGs): rank 0's, incl. an auxiliary head
    distributed.broadcast_modules([algo.policy, *algo.extra_modules()])
    ctx = RunContext(algo, config, run_dir, t.num_updates)
    ramp = _severity_ramp(cfg, algo.env, int(resume_state["update"]) if resume_state is not None else 0)
    set_rngs = _start(ctx, cfg, resume_state, rank_seed)
    if main:
        write_text(run_dir / "resolved_config.yaml", OmegaConf.to_yaml(OmegaConf.create(config)))
    set_rngs()  # last: building the run consumed random numbers
    ctx.stop_at = t.num_updates if t.stop_after is None else min(t.num_updates, algo.update + t.stop_after)
    ctx.session_start_update = algo.update
    if algo.update >= t.num_updates and main:
        log.info("run %s is already complete (%d updates); nothing to do", run_dir, algo.update)
    callbacks = _callbacks(ctx, cfg, parts.val_env, show_progress, resume_state is not None)
    if ramp is not None:
        callbacks.insert(0, ramp)
    return _run_session(ctx, callbacks, stop)


def _run_session(ctx: RunContext, callbacks: list[Callback], stop: Any) -> TrainResult:
    """:func:`learn` this session's updates, then the result (files, speed, the signal that stopped it)."""
    algo = ctx.algo
    session_start, t_start = algo.update, time.perf_counter()
    try:
        learn(ctx, callbacks, stop)
        distributed.barrier()  # nobody leaves before rank 0 has written its files
    finally:
        algo.env.close()
    session_time = time.perf_counter() - t_start
    if algo.update < ctx.num_updates and not stop.requested and distributed.is_main():
        log.info("stopped at update %d of %d; re-run the same command to resume", algo.update, ctx.num_updates)
    steps = (algo.update - session_start) * algo.steps_per_update * distributed.world_size()
    return TrainResult(
        run_dir=ctx.run_dir,
        updates=algo.update,
        env_steps=algo.env_steps,
        completed=algo.update >= ctx.num_updates,
        latest=ctx.latest_path if ctx.latest_path.is_file() else None,
        best=ctx.best_path if ctx.best_path.is_file() else None,
        best_val_eps=ctx.best_val_eps,
        last_val=ctx.last_val,
        steps_per_second=steps / session_time if session_time > 0 else math.nan,
        stopped_by=stop.signum,
    )
