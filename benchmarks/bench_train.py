"""Training throughput of the PPO baseline: env steps per second and where the time goes.

    python benchmarks/bench_train.py                       # CPU: 128x128 and 256x256, 16 envs
    python benchmarks/bench_train.py --device cuda         # + the paper's settings and 256 / 1024 envs
    python benchmarks/bench_train.py --sizes 128 --updates 3 --rollout-steps 32 --threads 1

Each setting builds the real training pieces (panorama bank, simulator, sampled episodes of all three
difficulties, ``FindViewEnv``, the paper's early-fusion policy with GRU 512, ``PPOTrainer`` with 4 PPO
epochs), runs one warm-up update (panorama decoding, allocator warm-up), then ``--updates`` timed ones.
Phases (seconds per update, from ``PPOTrainer.timings``):

- ``env``: ``FindViewEnv.step`` (rendering the new views, rewards, episode bookkeeping, resets);
- ``fwd``: the policy forward pass during the rollout (``Policy.act``);
- ``other``: the rest of the rollout loop (storage copies, episode records);
- ``update``: GAE + 4 PPO epochs (forward + backward + Adam).

``non-net`` = (env + other) / total: the share of time outside the network's forward / backward
(target < 25%). Panoramas: the SUN360 images of ``$FINDVIEW_SUN360_MINI`` (or
``$FINDVIEW_SUN360_MINI``) when present, else 8 procedural 1024x512 panoramas made on the fly.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from findview.build import build_sampled_env
from findview.config import SimConfig, TaskConfig
from findview.dataset import EpisodeSampler, ImageEntry
from findview.sim import resolve_device
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo import PPOConfig
from findview_baselines.rl.ppo_trainer import PPOTrainer, no_distribution_validation

REPO = Path(__file__).resolve().parents[1]


@dataclass
class Setting:
    size: int
    num_envs: int
    rollout_steps: int
    num_mini_batches: int = 1


@dataclass
class Result:
    setting: Setting
    steps_per_s: float
    env: float
    fwd: float
    other: float
    update: float

    @property
    def total(self) -> float:
        return self.env + self.fwd + self.other + self.update

    @property
    def non_network_share(self) -> float:
        return (self.env + self.other) / self.total


def find_panoramas(tmp: Path) -> list[ImageEntry]:
    """sun360_mini if available, else a few procedural panoramas written to ``tmp``."""
    mini = Path(os.environ.get("FINDVIEW_SUN360_MINI", "") or "/nonexistent")  # the sun360_mini folder, if you have it
    files = sorted(mini.rglob("*.jpg")) if mini.is_dir() else []
    if files:
        return [ImageEntry(str(f), f.parent.name) for f in files]
    import cv2

    from findview.dataset import generate_panorama

    entries = []
    for i, kind in enumerate(("room", "landscape", "village", "room") * 2):
        path = tmp / f"synth_{i}.png"
        cv2.imwrite(str(path), cv2.cvtColor(generate_panorama(i, kind, 1024), cv2.COLOR_RGB2BGR))
        entries.append(ImageEntry(str(path), kind))
    return entries


def run_setting(setting: Setting, images: list[ImageEntry], device: torch.device, updates: int) -> Result:
    """One warm-up update, then ``updates`` timed ones; returns steps/s and seconds per update per phase."""
    torch.manual_seed(0)
    sim_cfg = SimConfig(fov=90, height=setting.size, width=setting.size, device=str(device), bank_mb=4096)
    sampler = EpisodeSampler(images, 90, seed=0)
    env = build_sampled_env(sim_cfg, TaskConfig(), sampler, setting.num_envs)
    env.source.level = 3
    policy = Policy(setting.size, setting.size, "early_fusion", 512).to(device)
    cfg = PPOConfig(rollout_steps=setting.rollout_steps, num_mini_batches=setting.num_mini_batches)
    trainer = PPOTrainer(env, policy, cfg, total_updates=1_000_000, seed=0)
    with no_distribution_validation():
        trainer.start()
        trainer.train_update()  # warm-up
        trainer.pop_timings()
        start = time.perf_counter()
        for _ in range(updates):
            trainer.train_update()
        wall = time.perf_counter() - start
    t = trainer.pop_timings()
    env.close()
    steps = updates * setting.rollout_steps * setting.num_envs
    return Result(
        setting,
        steps_per_s=steps / wall,
        env=t["env_step"] / updates,
        fwd=t["policy_forward"] / updates,
        other=t["rollout_other"] / updates,
        update=t["update"] / updates,
    )


def print_table(results: list[Result], device: torch.device) -> None:
    threads = f", {torch.get_num_threads()} torch threads" if device.type == "cpu" else ""
    print(f"\nPPO training throughput on {device}{threads} (seconds per update per phase)")
    header = f"{'view':>9} {'envs':>5} {'T':>4} {'mb':>3} | {'steps/s':>8} | {'env':>7} {'fwd':>7} {'other':>7} {'update':>8} | {'non-net':>7}"
    print(header)
    print("-" * len(header))
    for r in results:
        s = r.setting
        print(
            f"{s.size:>4}x{s.size:<4} {s.num_envs:>5} {s.rollout_steps:>4} {s.num_mini_batches:>3} | {r.steps_per_s:>8.1f} | "
            f"{r.env:>7.3f} {r.fwd:>7.3f} {r.other:>7.3f} {r.update:>8.3f} | {100 * r.non_network_share:>6.1f}%"
        )


def main(argv: list[str] | None = None) -> list[Result]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (default cpu)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[128, 256], help="view sizes (square)")
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--rollout-steps", type=int, default=None, help="default: 32 on CPU, 128 on CUDA")
    parser.add_argument("--updates", type=int, default=None, help="timed updates (default: 2 on CPU, 5 on CUDA)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--many-envs", type=int, nargs="*", default=[256, 1024], help="CUDA only: extra env counts at 256x256")
    args = parser.parse_args(argv)

    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    cuda = device.type == "cuda"
    rollout = args.rollout_steps or (128 if cuda else 32)
    updates = args.updates or (5 if cuda else 2)
    settings = [Setting(size, args.num_envs, rollout) for size in args.sizes]
    if cuda:
        for n in args.many_envs:
            # keep the rollout storage (~2 * T * N * 3 * 256^2 bytes) and one mini-batch's activations in memory
            steps = 128 if n <= 256 else 32
            settings.append(Setting(256, n, steps, num_mini_batches=max(1, n * steps // 8192)))

    with tempfile.TemporaryDirectory() as tmp:
        images = find_panoramas(Path(tmp))
        print(f"{len(images)} panoramas; {updates} timed updates per setting after one warm-up")
        results = []
        for setting in settings:
            try:
                results.append(run_setting(setting, images, device, updates))
            except torch.OutOfMemoryError:
                print(f"out of memory: {setting}")
                torch.cuda.empty_cache()
                continue
            print_table(results[-1:], device)
    print_table(results, device)
    return results


if __name__ == "__main__":
    main()
