"""Does a 4x-environments PPO run learn as well per env step as the base run? (issue 11, batch scaling)

Scaling rule under test: PPO's batch per update is ``num_envs * rollout_steps`` samples. When the number
of environments grows by ``k`` (more envs on one GPU, or ``k`` DD-PPO ranks whose gradients are
averaged), keep the **samples per gradient step** and the epochs fixed, i.e. multiply
``trainer.ppo.num_mini_batches`` by ``k`` and keep ``trainer.ppo.lr``: the run then takes the same number of
gradient steps per env step as the base run. The alternative ("naive": same ``num_mini_batches``, so
``k`` times larger mini-batches and ``k`` times fewer gradient steps per env step) is run beside it, and
optionally the square-root rule (naive plus ``lr * sqrt(k)``).

The world is the colour-wheel toy world of the learning test (yaw only, easy episodes, 48x48 views,
GRU 64, bell reward: see ``tests/test_learning.py``), where the base run learns within ~77k env steps.
Every run gets the same env-step budget; ``train()`` runs in segments (``trainer.stop_after``) and after
each segment ``latest.pth`` is evaluated greedily on the same 48 fixed easy episodes.

    python benchmarks/bench_lr_scaling.py --out benchmarks/results            # ~15 min on 2 cores
    python benchmarks/bench_lr_scaling.py --quick --out /tmp/lr                # smoke run

Writes ``lr_scaling.csv`` (run, seed, env_steps, updates, wall_s, eps, omega_stop, spl) and
``lr_scaling.png`` (eps against env steps, drawn with OpenCV) into ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import tempfile
import time
from pathlib import Path

import findview  # noqa: F401  (thread policy before torch loads)
import cv2
import numpy as np
import torch

from findview.build import build_static_env
from findview.dataset import EpisodeSampler, ImageEntry
from findview.dataset.synthetic.colour_wheel import write_colour_wheel_folder
from findview.metrics import aggregate
from findview.utils import atomic_write, write_text
from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.cli import compose_config
from findview_baselines.evaluation.harness import run_episodes
from findview_baselines.rl.policy import build_policy
from findview_baselines.rl.checkpoint import load_policy  # noqa: E402
from findview_baselines.training import train

SIZE = 48
MAX_STEPS = 200
EVAL_EPISODES = 48
BASE_ENVS = 16
ROLLOUT = 16

TOY_WORLD = {
    "dataset": "folder", "dataset.name": "colour_wheel", "dataset.episode_pitch_bound": 0,
    "dataset.splits_to_make": "[]",
    "sim.height": SIZE, "sim.width": SIZE, "sim.device": "cpu", "sim.prefetch_workers": 0,
    "task.max_steps": MAX_STEPS, "task.pitch_bound": 0,
    "task.reward.name": "bell", "task.reward.alpha": 20.0, "task.reward.beta": 2.0, "task.reward.dist_coef": 1.0,
    "agent.hidden_size": 64, "trainer.ppo.rollout_steps": ROLLOUT, "trainer.ppo.entropy_coef": 0.01,
    "trainer.ppo.gamma": 0.9, "trainer.ppo.gae_lambda": 0.8, "trainer.ppo.ppo_epochs": 2,
    "trainer.torch_threads": 1, "trainer.val_interval": 0, "trainer.val_at_end": False,
    "trainer.log_interval": 1000, "trainer.checkpoint_interval": 0, "trainer.progress": False,
    "scheduler.num_levels": 1,
}


def runs_for(scale: int, base_lr: float, base_mini_batches: int, with_sqrt: bool) -> dict[str, dict[str, float]]:
    """name -> (num_envs, num_mini_batches, lr) of the compared runs."""
    runs = {
        "base": {"num_envs": BASE_ENVS, "num_mini_batches": base_mini_batches, "lr": base_lr},
        f"{scale}x_envs_scaled": {"num_envs": BASE_ENVS * scale, "num_mini_batches": base_mini_batches * scale, "lr": base_lr},
        f"{scale}x_envs_naive": {"num_envs": BASE_ENVS * scale, "num_mini_batches": base_mini_batches, "lr": base_lr},
    }
    if with_sqrt:
        runs[f"{scale}x_envs_sqrt_lr"] = {
            "num_envs": BASE_ENVS * scale, "num_mini_batches": base_mini_batches, "lr": base_lr * math.sqrt(scale),
        }
    return runs


def evaluate(cfg, checkpoint: Path, episodes) -> dict[str, float]:
    """Greedy eps / omega_stop / SPL of ``checkpoint`` on the fixed ``episodes``."""
    from findview.config import SimConfig
    from findview_baselines.cli import validate_config

    typed = validate_config(cfg)
    policy = build_policy(typed.agent, SIZE, SIZE)
    load_policy(checkpoint, policy)
    sim_cfg = SimConfig(fov=90, height=SIZE, width=SIZE, device="cpu", prefetch_workers=0)
    env = build_static_env(sim_cfg, typed.task, episodes, 16, max_steps=MAX_STEPS)
    return aggregate(run_episodes(env, PPOAgent(policy, 16), progress=False)[0])


def plot(rows: list[dict], path: Path) -> None:
    """eps (y) against env steps (x), one polyline per run (mean over seeds), legend top right."""
    w, h, m = 900, 520, 70
    colours = [(200, 80, 0), (0, 160, 0), (0, 0, 220), (160, 0, 160)]
    img = np.full((h, w, 3), 255, np.uint8)
    names = list(dict.fromkeys(r["run"] for r in rows))
    xmax = max(r["env_steps"] for r in rows)
    ymax = max(max(r["eps"] for r in rows), 1.0) * 1.05
    X = lambda x: int(m + (w - 2 * m) * x / xmax)  # noqa: E731
    Y = lambda y: int(h - m - (h - 2 * m) * y / ymax)  # noqa: E731
    cv2.line(img, (m, h - m), (w - m, h - m), (0, 0, 0), 1)
    cv2.line(img, (m, m), (m, h - m), (0, 0, 0), 1)
    for k in range(6):
        x, y = xmax * k / 5, ymax * k / 5
        cv2.putText(img, f"{x / 1000:.1f}k" if xmax < 20000 else f"{x / 1000:.0f}k", (X(x) - 12, h - m + 20), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
        cv2.putText(img, f"{y:.0f}", (m - 40, Y(y) + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1)
    cv2.putText(img, "env steps", (w // 2 - 40, h - 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1)
    cv2.putText(img, "greedy eps (deg), 48 fixed easy episodes", (m, m - 25), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 0, 0), 1)
    for i, name in enumerate(names):
        steps = sorted({r["env_steps"] for r in rows if r["run"] == name})
        pts = [(X(s), Y(float(np.mean([r["eps"] for r in rows if r["run"] == name and r["env_steps"] == s]))))
               for s in steps]
        colour = colours[i % len(colours)]
        cv2.polylines(img, [np.array(pts, np.int32)], False, colour, 2)
        for p in pts:
            cv2.circle(img, p, 4, colour, -1)
        cv2.putText(img, name, (w - m - 220, m + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1)
    ok, png = cv2.imencode(".png", img)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode {path}")
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(png.tobytes()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for lr_scaling.csv / .png")
    ap.add_argument("--scale", type=int, default=4, help="environment multiplier k (default 4)")
    ap.add_argument("--budget", type=int, default=76800, help="env steps per run (default 76800)")
    ap.add_argument("--segments", type=int, default=5, help="evaluations per run (default 5)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--mini-batches", type=int, default=2, help="num_mini_batches of the base run")
    ap.add_argument("--sqrt", action="store_true", help="also run the square-root lr rule")
    ap.add_argument("--quick", action="store_true", help="smoke run: budget 2*k*16*16*2 steps, 2 segments")
    args = ap.parse_args(argv)
    if args.quick:
        args.budget, args.segments = 2 * args.scale * BASE_ENVS * ROLLOUT * 2, 2
    big = BASE_ENVS * args.scale * ROLLOUT * args.segments
    if args.budget % big:
        ap.error(f"--budget {args.budget} must be a multiple of {big} (k * 16 envs * {ROLLOUT} steps * segments)")

    torch.set_num_threads(1)
    work = Path(tempfile.mkdtemp(prefix="findview_lr_scaling_"))
    root = work / "panoramas"
    write_colour_wheel_folder(root, count=10, first_seed=200)
    images = [ImageEntry(str(p), "colour_wheel") for p in sorted(root.glob("*.png"))]
    sampler = EpisodeSampler(images, 90, seed=12345, max_steps=MAX_STEPS, pitch_bound=0)
    episodes = [sampler.sample("easy") for _ in range(EVAL_EPISODES)]

    rows: list[dict] = []
    runs = runs_for(args.scale, args.lr, args.mini_batches, args.sqrt)
    for seed in args.seeds:
        for name, r in runs.items():
            n_updates = args.budget // (r["num_envs"] * ROLLOUT)
            seg = n_updates // args.segments
            setup = {**TOY_WORLD, "dataset.root": str(root), "dataset.out_dir": str(work / "dataset"),
                     "trainer.num_envs": r["num_envs"], "trainer.num_updates": n_updates, "trainer.seed": seed,
                     "trainer.ppo.num_mini_batches": r["num_mini_batches"], "trainer.ppo.lr": r["lr"]}
            run_dir = work / f"{name}_s{seed}"
            wall = 0.0
            for k in range(1, args.segments + 1):
                cfg = compose_config("train", [f"{a}={b}" for a, b in {**setup, "trainer.stop_after": seg}.items()])
                start = time.perf_counter()
                result = train(cfg, run_dir)
                wall += time.perf_counter() - start
                m = evaluate(cfg, result.latest, episodes)
                row = {"run": name, "seed": seed, "env_steps": result.env_steps, "updates": result.updates,
                       "wall_s": round(wall, 1), "eps": round(m["eps"], 3), "omega_stop": round(m["omega_stop"], 3),
                       "spl": round(m["spl"], 4), **{f"cfg_{a}": b for a, b in r.items()}}
                rows.append(row)
                print(f"{name:>22} seed {seed}  {row['env_steps']:>6} steps  {row['updates']:>4} upd  "
                      f"{row['wall_s']:>6.0f}s  eps {row['eps']:6.2f}  stop {row['omega_stop']:.2f}  spl {row['spl']:.3f}",
                      flush=True)
    base_final = np.mean([r["eps"] for r in rows if r["run"] == "base" and r["env_steps"] == args.budget])
    print(f"\nfinal greedy eps at {args.budget} env steps (mean over seeds {args.seeds}), ratio to base:")
    for name in runs:
        final = np.mean([r["eps"] for r in rows if r["run"] == name and r["env_steps"] == args.budget])
        print(f"  {name:>22}: eps {final:6.2f}  ({final / max(base_final, 1e-9):.2f}x base)")
    args.out.mkdir(parents=True, exist_ok=True)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_text(args.out / "lr_scaling.csv", buf.getvalue())
    plot(rows, args.out / "lr_scaling.png")
    print(f"wrote {args.out / 'lr_scaling.csv'} and {args.out / 'lr_scaling.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
