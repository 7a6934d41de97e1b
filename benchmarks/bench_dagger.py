"""DAgger update time of the robust preset, with and without the cache of the fixed encoder inputs.

    python benchmarks/bench_dagger.py                      # 64x64 phase policy, 16 envs, 4 timed updates each
    python benchmarks/bench_dagger.py --variant robust --updates 8 --threads 2

The ``direct`` / ``robust`` / ``phase`` policies begin with parameter-free comparisons of view and target (cost
volumes, phase correlation). ``trainer.dagger.cache_fixed_features=true`` (the default) computes them once
per step, when the learner acts in the rollout, and the buffer keeps them; ``false`` recomputes them at every gradient step (``epochs`` = 8 in the robust
preset: each buffered step is forwarded about 8 times). Both settings build the trainer of
``+experiment=robust``, composed as ``tools/train.py`` does (64x64 views, GRU 256, 16 envs, 32-step rollouts, 16 sequences of 16 steps per gradient step, all three
difficulties, every corruption at severity 1-5), run one warm-up update, then ``--updates`` timed ones;
the two settings alternate (``--rounds``) so a change in machine load hits both. Prints seconds per update
(rollout and gradient steps) and the ratio. Panoramas: ``$FINDVIEW_SUN360_MINI`` when set, else procedural.

``--compare overlap`` times ``trainer.dagger.overlap_rollout=false`` against ``true`` instead (both with the cache):
the rollout in a second thread beside the gradient steps, on two cores; ``--updates`` includes the first, sequential
update of a fresh trainer after the warm-up, so use 8 or more.

    python benchmarks/bench_dagger.py --compare overlap --updates 8
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import findview  # noqa: F401  (thread policy before torch loads)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_train import find_panoramas  # noqa: E402

from findview.build import build_sampled_env  # noqa: E402
from findview.dataset import EpisodeSampler  # noqa: E402
from findview_baselines.config import compose_config, typed_config  # noqa: E402
from findview_baselines.rl.dagger import DAggerTrainer  # noqa: E402
from findview_baselines.rl.policy import build_policy  # noqa: E402


def make_trainer(images, variant: str, cache: bool, seed: int = 0, overlap: bool = False) -> DAggerTrainer:
    """The robust preset's trainer (configs/experiment/robust.yaml, composed as tools/train.py does) on sampled
    episodes of every difficulty."""
    torch.manual_seed(seed)
    cfg = typed_config(compose_config("train", [
        "+experiment=robust", f"agent.variant={variant}", f"trainer.dagger.cache_fixed_features={cache}",
        f"trainer.dagger.overlap_rollout={overlap}",
    ]))
    sampler = EpisodeSampler(images, cfg.sim.fov, seed=seed, max_steps=cfg.task.max_steps)
    env = build_sampled_env(cfg.sim, cfg.task, sampler, cfg.trainer.num_envs, corruption_cfg=cfg.corruption)
    env.source.level = 3
    policy = build_policy(cfg.agent, cfg.sim.height, cfg.sim.width)
    trainer = DAggerTrainer(env, policy, cfg.trainer.dagger, total_updates=cfg.trainer.num_updates, seed=seed,
                            revisit_penalty=cfg.agent.revisit_penalty)
    trainer.start()
    return trainer


def time_updates(trainer: DAggerTrainer, updates: int) -> tuple[float, float]:
    """Seconds per update: (whole update, gradient steps alone)."""
    trainer.train_update()  # warm-up: panorama decoding, allocator
    trainer.pop_timings()
    start = time.perf_counter()
    for _ in range(updates):
        trainer.train_update()
    wall = time.perf_counter() - start
    return wall / updates, trainer.pop_timings()["update"] / updates


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", default="phase", choices=("direct", "robust", "phase"))
    parser.add_argument("--compare", default="cache", choices=("cache", "overlap"),
                        help="cache: fixed inputs recomputed vs cached; overlap: rollout after vs beside the gradient steps")
    parser.add_argument("--updates", type=int, default=4, help="timed updates per setting and round")
    parser.add_argument("--rounds", type=int, default=2, help="alternations of the two settings")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.compare == "cache":  # (label, make_trainer keywords): the reference first
        settings = [("recomputed every step", {"cache": False}), ("cached (default)", {"cache": True})]
    else:
        settings = [("one after the other", {"cache": True}), ("overlap_rollout", {"cache": True, "overlap": True})]
    with tempfile.TemporaryDirectory() as tmp:
        images = find_panoramas(Path(tmp))
        times: dict[str, list[tuple[float, float]]] = {label: [] for label, _ in settings}
        for _ in range(args.rounds):
            for label, kwargs in settings:
                times[label].append(time_updates(make_trainer(images, args.variant, **kwargs), args.updates))
    print(f"\nDAgger update of the robust preset ({args.variant}; configs/experiment/robust.yaml), "
          f"{args.threads} thread(s), {args.rounds} x {args.updates} updates per setting")
    name = "fixed inputs" if args.compare == "cache" else "rollout"
    print(f"{name:>22} | {'s / update':>10} | {'gradient steps':>14}")
    mean = {label: [sum(x[i] for x in times[label]) / len(times[label]) for i in (0, 1)] for label in times}
    for label, _ in settings:
        print(f"{label:>22} | {mean[label][0]:>10.2f} | {mean[label][1]:>14.2f}")
    (ref, _), (new, _) = settings
    print(f"ratio {ref} / {new}: update {mean[ref][0] / mean[new][0]:.2f}x, "
          f"gradient steps {mean[ref][1] / mean[new][1]:.2f}x")


if __name__ == "__main__":
    main()
