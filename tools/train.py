"""Train the learned FindView agent (PPO, or imitation of the oracle with ``trainer=dagger``).

    python tools/train.py agent=ppo dataset=<name> [sim=fov60] [trainer.num_updates=30000] [init_from=<ckpt>]
    python tools/train.py +experiment=quickstart

The run folder (``hydra.run.dir``, default ``outputs/train/<dataset>/<agent>_<variant>_fov<F>_<H>x<W>``)
holds ``checkpoints/latest.pth`` (resume state), ``checkpoints/best.pth`` (lowest mean val eps),
TensorBoard scalars in ``tb/`` and the config. Re-running the same command resumes where it stopped
(``trainer.resume=false`` starts over). SIGTERM or Ctrl-C stop at the next safe point, write
``latest.pth`` and exit with 143 / 130. Every key is documented in ``findview_baselines/config.py``.

Several processes (DD-PPO, ``trainer.num_envs`` per process; docs/CLUSTER.md)::

    torchrun --standalone --nproc_per_node=K tools/train.py ... trainer.distributed=true

Only rank 0 writes the run folder (Hydra's files, log, checkpoints, TensorBoard); the other ranks log to
the console. A signal to any rank (SIGTERM, SIGINT, SIGUSR1) stops every rank at the same safe point.

Exit status: 0 done (or stopped by ``trainer.stop_after``), 1 training diverged, 2 a problem with the
input (one line on stderr), 128 + signal when stopped by a signal (143 SIGTERM, 130 SIGINT, 138 SIGUSR1).
"""

from __future__ import annotations

import logging
import os
import sys

from findview_baselines.cli import ToolContext, run_tool
from findview_baselines.config import TrainConfig

log = logging.getLogger("train")


def main(cfg: TrainConfig, ctx: ToolContext) -> None:
    """Train (or resume) into the run folder; exit 1 when the training diverged."""
    from findview_baselines.training import TrainingDiverged, train

    try:
        result = train(cfg, ctx.run_dir)
    except TrainingDiverged as err:
        print(f"train: {err}", file=sys.stderr, flush=True)
        sys.exit(1)
    status = "complete" if result.completed else "stopped early (re-run to resume)"
    best = f", best val eps {result.best_val_eps:.3f} ({result.best})" if result.best_val_eps is not None else ""
    log.info(
        "%s: %d updates, %d env steps, %.0f steps/s this session%s; latest: %s",
        status, result.updates, result.env_steps, result.steps_per_second, best, result.latest,
    )


def _rank_overrides(argv: list[str]) -> tuple[list[str], bool]:
    """(argv, whether to pre-check the run folder) for this process: under torchrun, ranks other than 0
    write no Hydra files and log to the console only (rank 0 writes the run folder), and skip the
    pre-check of the folder's lock (rank 0 may already hold it)."""
    rank = int(os.environ.get("RANK", "0") or 0)
    if rank == 0:
        return argv, True
    return [*argv, "hydra.output_subdir=null", "hydra/job_logging=stdout"], False


if __name__ == "__main__":
    sys.argv[1:], check_dir = _rank_overrides(sys.argv[1:])
    run_tool("train", main, check_run_dir=check_dir)
