"""The training loop: :func:`learn` runs updates of a :class:`~findview_baselines.rl.trainer_base.Trainer` until
the run is done or a stop is requested, and hands every update's stats to the :class:`Callback` s; the
:class:`RunContext` is what the callbacks share (the trainer, the run's files, its best validation)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import checkpoint_payload, save_checkpoint
from findview_baselines.rl.trainer_base import Trainer, UpdateAbandoned

log = logging.getLogger(__name__)

__all__ = ["TrainingDiverged", "RunContext", "Callback", "learn", "REPLICATED_KEYS"]

#: trainer-state entries that are the same on every rank (saved once, by rank 0)
REPLICATED_KEYS = ("signature", "policy", "ppo", "optimizer", "aux_head", "kind")


class TrainingDiverged(RuntimeError):
    """A non-finite loss / gradient / weight stopped training; the last good checkpoint was kept."""


@dataclass
class RunContext:
    """What the callbacks share: the trainer, the run's files and its bookkeeping.

    ``config`` is the run's resolved config as a plain dict (stored in every checkpoint)."""

    algo: Trainer
    config: dict[str, Any]
    run_dir: Path
    num_updates: int
    best_val_eps: float | None = None
    last_val: dict[str, Any] | None = None
    last_saved_update: int = -1
    stop_at: int = 0
    """The update this session ends at (``trainer.stop_after`` or the run's last)."""
    session_start_update: int = 0
    stopping: bool = False
    """A stop was agreed during the last update: callbacks skip what can wait (a scheduled validation)."""
    validated_at: int = -1
    failed: bool = False
    """The loop raised: under torchrun no more collectives (the other ranks may be gone)."""

    @property
    def latest_path(self) -> Path:
        return self.run_dir / "checkpoints" / "latest.pth"

    @property
    def best_path(self) -> Path:
        return self.run_dir / "checkpoints" / "best.pth"

    def checkpoint(self, with_trainer: bool) -> dict[str, Any]:
        """The checkpoint payload (``best.pth`` without the trainer's resume state)."""
        algo = self.algo
        return checkpoint_payload(algo.policy, algo.update, algo.env_steps, self.config, self.last_val,
                                  self.best_val_eps, algo.state_dict() if with_trainer else None)

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


def _diverged(ctx: RunContext, err: FloatingPointError) -> TrainingDiverged:
    kept = (
        f"the last good checkpoint {ctx.latest_path} (update {ctx.last_saved_update}) was kept"
        if ctx.latest_path.is_file() and ctx.last_saved_update >= 0
        else "no checkpoint had been written yet"
    )
    return TrainingDiverged(
        f"training diverged at update {ctx.algo.update + 1}: {err}; {kept}. Lower the learning rate or "
        f"check the inputs, then re-run to resume from the last checkpoint."
    )


def learn(ctx: RunContext, callbacks: Sequence[Callback], stop: Any) -> None:
    """Run updates until ``ctx.stop_at`` updates are done or a stop is requested; callbacks do the rest.

    ``stop`` is a :class:`~findview_baselines.rl.safety.StopOnSignal`, or under torchrun an
    :class:`~findview_baselines.rl.distributed.AgreedStop` (every rank stops at the same point); the stats of
    every update are reduced over the ranks before the callbacks see them."""
    algo = ctx.algo
    try:
        stopping = stop.agree()
        while algo.update < ctx.stop_at and not stopping:
            try:
                stats = algo.train_update(stop)
            except UpdateAbandoned as err:
                log.info("%s", err)
                stop.agree()  # every rank learns the signal (with preemption, some only saw it abandon)
                break
            except FloatingPointError as err:
                raise _diverged(ctx, err) from err
            stats = distributed.reduce_stats(stats)
            # a stop asked for during this update (agreed by every rank): the callbacks skip what can wait
            # (a scheduled validation) and the session ends after them, writing latest.pth
            stopping = ctx.stopping = stop.agree()
            for cb in callbacks:
                cb.on_update(ctx, stats)
    except BaseException:
        ctx.failed = True
        raise
    finally:
        if not ctx.failed:
            stop.close()
        for cb in callbacks:
            cb.on_end(ctx, stop.requested)
