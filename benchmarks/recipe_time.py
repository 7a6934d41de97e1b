"""How long the FoV-90 robust agent's recipe takes to train on this machine: an estimate in about a minute.

    python benchmarks/recipe_time.py                          # the built-in synthetic data (made if missing)
    python benchmarks/recipe_time.py --updates 20 dataset=sun360_indoor dataset.root=<sun360_mini> \
        dataset.out_dir=data/sun360_mini_indoor dataset.name=sun360_mini_indoor dataset.episodes_per_image=10
    python benchmarks/recipe_time.py --recipe fov60               # the FoV-60 file's three stages

The recipe is the five commands of ``pretrained/findview_sun360mini_indoor_robust.pth``'s "Make it"
(pretrained/README.md): stage 1 ``+experiment=robust``, stage 2 ``+experiment=robust_memory agent.pitch_warps=true``,
stage 3 two ``+experiment=robust_polish`` runs side by side, stage 4 ``+experiment=robust_wide``, each on one torch
thread per thread of work (``trainer.torch_threads=1``). Each stage's trainer is built as ``tools/train.py`` builds
it (``findview_baselines.training.build.build_run``, fresh weights: the time of an update does not depend on them)
in a process of its own, and stage 3's two in two processes at once, as the card runs them. After ``--warmup``
updates (the first runs its rollout and gradient steps one after the other), ``--updates`` are timed; the
seconds per update times the preset's ``trainer.num_updates`` is the stage's estimate. Start-up, data loading and
the two validations (about a minute in all) are not counted. Overrides after the options (the card's dataset ones)
go to every run; the panoramas change an update's time little (the views are 64x64 pixels).

Prints per stage: the updates, the seconds per update, the estimated minutes; then the total and its ratio to
the hour the issue asks for. ``--recipe fov60`` times the three commands of
``pretrained/findview_sun360mini_indoor_robust_fov60.pth`` instead (since session 53 made as the FoV-90 file is:
the rollout beside the gradient steps, validation only at each stage's end). On the machine of session 51 it said
52.4 minutes (51.3 with ``--updates 30``) where the FoV-90 file's five commands took 56.5 end to end
(benchmarks/RESULTS.md, "Session 51"): read it as about a tenth short. For the FoV-60 recipe in session 53 it
said 44.6 minutes where the three commands took 43.0 end to end.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass

GOAL_MINUTES = 60.0  # the hour on two CPU cores that training the shipped agent should fit in


@dataclass(frozen=True)
class Stage:
    """One stage of the recipe: its name, the runs side by side (each a list of overrides)."""

    name: str
    runs: tuple[tuple[str, ...], ...]


STAGES_FOV90 = (  # pretrained/findview_sun360mini_indoor_robust.pth
    Stage("1: +experiment=robust", (("+experiment=robust",),)),
    Stage("2: +experiment=robust_memory", (("+experiment=robust_memory", "agent.pitch_warps=true", "trainer.seed=1"),)),
    Stage("3: two +experiment=robust_polish side by side", (
        ("+experiment=robust_polish", "trainer.dagger.search_weight=0.6"),
        ("+experiment=robust_polish", "trainer.dagger.search_weight=0.3"),
    )),
    Stage("4: +experiment=robust_wide", (("+experiment=robust_wide",),)),
)
STAGES_FOV60 = (  # pretrained/findview_sun360mini_indoor_robust_fov60.pth (since session 53)
    Stage("1: +experiment=robust sim.fov=60", (("+experiment=robust", "sim.fov=60", "trainer.seed=1"),)),
    Stage("2: +experiment=robust_memory sim.fov=60", (
        ("+experiment=robust_memory", "sim.fov=60", "agent.pitch_warps=true", "trainer.seed=2"),)),
    Stage("3: +experiment=robust_wide sim.fov=60", (
        ("+experiment=robust_wide", "sim.fov=60", "agent.wide_match_min_peak=0.75"),)),
)
RECIPES = {"fov90": STAGES_FOV90, "fov60": STAGES_FOV60}


def time_run(overrides: list[str], updates: int, warmup: int) -> dict[str, float]:
    """Build the trainer of ``overrides`` (composed as ``tools/train.py`` does, with ``trainer.torch_threads=1`` and
    no validation), run ``warmup`` updates, then time ``updates``, on the caller's thread settings (the ``--one``
    process applies ``tools/train.py``'s for one torch thread first). Returns ``s_per_update`` and the preset's
    ``num_updates``."""
    from findview_baselines.config import compose_config, typed_config
    from findview_baselines.training.build import build_run

    cfg = typed_config(compose_config("train", [*overrides, "trainer.torch_threads=1", "trainer.val_interval=0",
                                                "trainer.val_at_end=false"]))
    trainer = build_run(cfg, cfg.trainer.seed, progress=False).trainer
    trainer.start()
    for _ in range(warmup):
        trainer.train_update()
    start = time.perf_counter()
    for _ in range(updates):
        trainer.train_update()
    seconds = time.perf_counter() - start
    trainer.env.close()
    return {"s_per_update": seconds / updates, "num_updates": cfg.trainer.num_updates}


def run_stage(stage: Stage, updates: int, warmup: int, extra: list[str]) -> list[dict[str, float]]:
    """Each run of ``stage`` (with the ``extra`` overrides) in a process of its own, the runs at once; their
    :func:`time_run` results."""
    procs = [
        subprocess.Popen([sys.executable, __file__, "--one", json.dumps([*run, *extra]), "--updates", str(updates),
                          "--warmup", str(warmup)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for run in stage.runs
    ]
    results = []
    for proc, run in zip(procs, stage.runs):
        out, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"recipe_time: stage {stage.name} ({' '.join(run)}) failed:\n{err.strip()[-2000:]}")
        results.append(json.loads(out.strip().splitlines()[-1]))
    return results


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, default=10, help="timed updates per stage (default 10)")
    parser.add_argument("--warmup", type=int, default=2, help="updates before the timed ones (default 2)")
    parser.add_argument("--recipe", choices=tuple(RECIPES), default="fov90",
                        help="fov90: the FoV-90 robust file's four stages (default); fov60: the FoV-60 file's three")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # a JSON list of overrides: time one run, print JSON
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every run (the dataset's)")
    args = parser.parse_args(argv)
    if args.updates < 1 or args.warmup < 1:
        parser.error(f"--updates and --warmup must be >= 1 (got {args.updates} and {args.warmup})")
    if args.one is not None:  # a process of its own: the thread policy tools/train.py applies for torch_threads=1
        import findview  # noqa: F401  (thread policy before torch loads)
        from findview.runtime import configure_threads

        configure_threads(1)
        print(json.dumps(time_run(json.loads(args.one), args.updates, args.warmup)))
        return
    rows = []
    for stage in RECIPES[args.recipe]:
        results = run_stage(stage, args.updates, args.warmup, args.overrides)
        # side by side, the stage lasts as long as its slowest run
        seconds = max(r["s_per_update"] * r["num_updates"] for r in results)
        rows.append((stage, results, seconds))
        print(f"stage {stage.name}: {seconds / 60:.1f} min", flush=True)
    total = sum(seconds for _, _, seconds in rows)
    print(f"\nThe {args.recipe} robust recipe on this machine ({os.cpu_count()} CPUs; {args.updates} timed updates "
          f"per run after {args.warmup}), start-up and validations not counted:")
    print(f"{'stage':<48} | {'updates':>9} | {'s / update':>11} | {'minutes':>7}")
    for stage, results, seconds in rows:
        updates = " + ".join(str(int(r["num_updates"])) for r in results)
        rate = " / ".join(f"{r['s_per_update']:.2f}" for r in results)
        print(f"{stage.name:<48} | {updates:>9} | {rate:>11} | {seconds / 60:>7.1f}")
    print(f"{'all':<48} | {'':>9} | {'':>11} | {total / 60:>7.1f}")
    print(f"ratio to the {GOAL_MINUTES:.0f}-minute goal: {total / 60 / GOAL_MINUTES:.2f}")


if __name__ == "__main__":
    main()
