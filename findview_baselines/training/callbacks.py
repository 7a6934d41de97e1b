"""The callbacks of a training run (:func:`findview_baselines.training.loop.learn`): the progress bar,
TensorBoard (:func:`tb_tag` names every stat a trainer reports), validation with ``best.pth``, ``latest.pth``
and the corruption-severity ramp."""

from __future__ import annotations

import logging
import time
from collections import deque
from pathlib import Path
from typing import Any, Mapping, Sequence

from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import save_checkpoint
from findview_baselines.training.loop import Callback, RunContext

log = logging.getLogger(__name__)

__all__ = [
    "tb_tag", "SCHEDULE_KEYS", "BOOKKEEPING_KEYS", "ProgressCallback", "TensorBoardCallback", "ValidationCallback",
    "CheckpointCallback", "SeverityRamp",
]

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


class _MetricWindow:
    """Recent finished training episodes (for the progress bar and TensorBoard)."""

    def __init__(self, size: int) -> None:
        self.records: deque[dict[str, Any]] = deque(maxlen=size)

    def add(self, records: Sequence[Mapping[str, Any]]) -> None:
        self.records.extend(dict(r) for r in records)

    def summary(self) -> dict[str, float]:
        """Mean return, eps, length, stop and success share of the window (``{}`` when empty)."""
        if not self.records:
            return {}
        n = len(self.records)
        stopped = [bool(r["called_stop"]) for r in self.records]
        success = [s and float(r["eps"]) == 0.0 for s, r in zip(stopped, self.records)]
        return {
            "reward": sum(float(r["return"]) for r in self.records) / n,
            "eps": sum(float(r["eps"]) for r in self.records) / n,
            "episode_length": sum(float(r["steps"]) for r in self.records) / n,
            "omega_stop": sum(stopped) / n,
            "success_rate": sum(success) / n,
        }


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
        self.window.add(stats["episodes"])
        recent = self.window.summary()
        self.bar.update(1)
        self.bar.set_postfix(
            sps=f"{self.steps_per_update / max(dt, 1e-9):.0f}", lvl=stats["level"],
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
        self._reset()

    def _reset(self) -> None:
        self.totals: dict[str, float] = {}
        self.counts: dict[str, int] = {}
        self.count, self.steps, self.t0 = 0, 0, time.perf_counter()

    def _accumulate(self, stats: Mapping[str, Any]) -> None:
        for key, value in stats.items():
            tag = tb_tag(key)
            if tag is None or not isinstance(value, (int, float)) or tag.startswith("schedule/"):
                continue
            self.totals[tag] = self.totals.get(tag, 0.0) + float(value)
            self.counts[tag] = self.counts.get(tag, 0) + 1
        self.count += 1
        self.steps += self.steps_per_update

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        self.window.add(stats["episodes"])
        self._accumulate(stats)
        update = ctx.algo.update
        if update % self.log_interval and update != ctx.stop_at:
            return
        elapsed = time.perf_counter() - self.t0
        scalars = {tag: v / self.counts[tag] for tag, v in self.totals.items()}
        scalars.update({f"train/{k}": v for k, v in self.window.summary().items()})
        for key in SCHEDULE_KEYS:
            if isinstance(stats.get(key), (int, float)):  # a stat some trainers report and others not
                scalars[f"schedule/{key}"] = float(stats[key])
        scalars["progress/update"] = float(update)
        scalars["perf/fps"] = self.steps / max(elapsed, 1e-9)
        scalars["perf/env_steps"] = float(ctx.algo.env_steps)
        scalars.update({f"time/{k}": v / self.count for k, v in ctx.algo.pop_timings().items()})
        for key, value in scalars.items():
            self.writer.add_scalar(key, value, ctx.algo.env_steps)
        self._reset()

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
    wrapper through the evaluation harness; keep ``best.pth`` (lowest mean val eps) and, with ``keep_all``,
    every validation's weights as ``val_u<update>.pth`` beside it. Ranks other than 0 pass ``val_env=None``:
    they keep rank 0's schedule (the collective checkpoint after it) in step."""

    def __init__(self, val_env: Any, agent: Any, interval: int, at_end: bool, tb: TensorBoardCallback | None,
                 keep_all: bool = False) -> None:
        self.env, self.agent = val_env, agent
        self.interval, self.at_end, self.tb, self.keep_all = interval, at_end, tb, keep_all

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
        if ctx.stopping:  # a signal asked to stop: write latest.pth now, validate another time
            if self.env is not None:
                log.info("stop requested: validation at update %d skipped", update)
            return
        ctx.validated_at = update  # on every rank: the checkpoint that follows is collective
        if self.env is None:
            return  # not rank 0
        ctx.last_val = self.validate(ctx)
        mean_eps = float(ctx.last_val["all"]["eps"])
        is_best = ctx.best_val_eps is None or mean_eps < ctx.best_val_eps
        if is_best:
            ctx.best_val_eps = mean_eps
        weights = ctx.checkpoint(with_trainer=False) if is_best or self.keep_all else None
        if self.keep_all:
            save_checkpoint(ctx.best_path.with_name(f"val_u{update:05d}.pth"), weights)
        if is_best:
            save_checkpoint(ctx.best_path, weights)
            log.info("new best val eps %.3f at update %d -> %s", mean_eps, update, ctx.best_path)
        if self.tb is not None:
            self.tb.add_validation(ctx.algo.env_steps, ctx.last_val, ctx.best_val_eps)


class CheckpointCallback(Callback):
    """``latest.pth`` every ``interval`` updates, after every validation and when the session ends."""

    def __init__(self, interval: int) -> None:
        self.interval = interval

    def on_update(self, ctx: RunContext, stats: Mapping[str, Any]) -> None:
        update = ctx.algo.update
        if (self.interval > 0 and update % self.interval == 0) or ctx.validated_at == update or update == ctx.stop_at:
            ctx.save_latest()

    def on_end(self, ctx: RunContext, stopped: bool) -> None:
        if ctx.failed and distributed.world_size() > 1:
            return  # a collective save could wait forever for a rank that failed; the last periodic one stays
        if (ctx.algo.update > ctx.session_start_update or stopped) and ctx.last_saved_update != ctx.algo.update:
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
