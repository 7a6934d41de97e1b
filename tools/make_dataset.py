"""Make a data set's splits and static val/test episode files (and the synthetic images).

Examples::

    python tools/make_dataset.py                                   # built-in synthetic panoramas
    python tools/make_dataset.py dataset=sun360_indoor dataset.root=/data/SUN360
    python tools/make_dataset.py dataset=folder dataset.root=/my/panos dataset.out_dir=data/mine \
        dataset.split=[0,0,1] dataset.episodes_per_image=3

Writes ``<out_dir>/splits.json`` and ``<out_dir>/episodes/<split>_fov<F>.json`` for every split in
``dataset.splits_to_make`` and every FoV in ``dataset.episode_fovs`` plus ``sim.fov``, then prints a
summary. The episodes depend on the ``dataset`` config only (``dataset.episode_seed``,
``episodes_per_image``, ``hard_rule``, ``episode_pitch_bound``, ``episode_max_steps``), never on ``task.*``
settings (docs/TASK.md, Datasets and splits). Known problems (bad image, missing folder, impossible
difficulty...) end the run with a one-line ``make_dataset: error: ...`` on stderr and exit status 2.
"""

from __future__ import annotations

from findview_baselines.cli import ToolContext, UserError, run_tool
from findview_baselines.config import MakeDatasetConfig


def main(cfg: MakeDatasetConfig, ctx: ToolContext) -> None:
    """Make (or reuse) the splits and episode files of ``cfg.dataset`` and print what was made."""
    from findview.dataset import SamplingError, prepare_dataset

    fovs = [float(f) for f in cfg.dataset.episode_fovs]
    if float(cfg.sim.fov) not in fovs:
        fovs.append(float(cfg.sim.fov))
    try:
        summary = prepare_dataset(
            cfg.dataset, fovs, force=cfg.force, progress=cfg.progress, log=lambda msg: print(msg, flush=True)
        )
    except (SamplingError, OSError) as err:
        raise UserError(str(err)) from err
    print(summary.format(), flush=True)


if __name__ == "__main__":
    run_tool("make_dataset", main)
