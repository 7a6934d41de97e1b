"""Train the FindView PPO baseline.

    python tools/train.py agent=ppo dataset=<name> [sim=fov60] [sim.height=128 sim.width=128]
        [trainer.num_updates=30000] [trainer.num_envs=16] [trainer.val_interval=1000] [init_from=<ckpt>]

The run folder (``hydra.run.dir``, default
``outputs/train/<dataset>/<agent>_<variant>_fov<F>_<H>x<W>``) holds ``checkpoints/latest.pth`` (resume
state), ``checkpoints/best.pth`` (lowest mean val eps), TensorBoard scalars in ``tb/`` and the config
(``.hydra/`` and ``resolved_config.yaml``). Re-running the same command resumes where it stopped
(``trainer.resume=false`` starts over). Ctrl-C once stops after the current update and writes
``latest.pth``. See ``configs/train.yaml`` for every option.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run from a checkout without `pip install -e .`
    sys.path.insert(0, str(REPO))

from findview_baselines.rl.trainer import TrainingDiverged, train  # noqa: E402

log = logging.getLogger("train")


def _precheck_run_dir(argv: list[str]) -> None:
    """Fail with a clear message before Hydra itself tries to create an unwritable run folder.

    Composes the config like Hydra will (single runs only; multirun and Hydra's own flags are left to
    Hydra) and checks write access to the resolved ``hydra.run.dir``.
    """
    if any(arg.startswith("-") for arg in argv):
        return
    from hydra import compose, initialize_config_dir

    from findview_baselines.rl.checkpoint import check_writable

    try:
        with initialize_config_dir(str(REPO / "configs"), version_base="1.3"):
            cfg = compose("train", overrides=argv, return_hydra_config=True)
            run_dir = str(cfg.hydra.run.dir)
    except Exception:  # a bad override etc.: let Hydra report it in its own words
        return
    try:
        check_writable(run_dir, "run folder (hydra.run.dir)")
    except PermissionError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)


@hydra.main(config_path="../configs", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        result = train(cfg, run_dir)
    except (TrainingDiverged, PermissionError, ValueError, FileNotFoundError) as err:
        log.error("%s", err)
        sys.exit(1)
    status = "complete" if result.completed else "stopped early (re-run to resume)"
    best = f", best val eps {result.best_val_eps:.3f} ({result.best})" if result.best_val_eps is not None else ""
    log.info(
        "%s: %d updates, %d env steps, %.0f steps/s this session%s; latest: %s",
        status, result.updates, result.env_steps, result.steps_per_second, best, result.latest,
    )


if __name__ == "__main__":
    _precheck_run_dir(sys.argv[1:])
    main()
