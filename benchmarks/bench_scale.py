"""End-to-end PPO training throughput as a curve over the number of environments.

    python benchmarks/bench_scale.py --device cpu --threads 1 --out outputs/bench_scale/cpu
    python benchmarks/bench_scale.py --device cuda --configs fp32 bf16+cl --out outputs/bench_scale/cuda
    python benchmarks/bench_scale.py --device cpu --num-envs 16 --configs fp32 fp32+cl bf16 bf16+cl

The paper's setting: 256x256 views, FoV 90 degrees, the early-fusion CNN with a 512-unit GRU, 4 PPO
epochs, sampled episodes of all three difficulties. For each number of environments ``N`` (default 16,
32, ..., 1024) and each configuration it builds the real training pieces (panorama bank, simulator,
``FindViewEnv``, policy via ``build_policy``, ``PPOTrainer``), runs one warm-up update, then
``--updates`` timed ones, and reports env steps per second *including* the PPO update (``N * T``
steps per update / wall-clock seconds per update) and the seconds per phase.

Configurations (``--configs``): ``fp32`` | ``bf16`` (agent.precision), with ``+cl`` for
agent.channels_last and ``+compile`` for agent.compile, e.g. ``bf16+cl``. Ratios are printed against the
smallest ``N`` of the same configuration (the curve) and against the first configuration at the same
``N`` (the options), all measured in the same run.

Rollout length ``T``: ``--rollout-steps`` (default 8 on CPU, so that a curve fits in minutes; on CUDA
``min(128, 65536 / N)``, the paper's 128 up to 512 envs). Mini-batches split the environments so that one
holds at most ``--mb-samples`` samples (``N * T / num_mini_batches``; default 512 on CPU, 8192 on CUDA)
to bound memory. The curve stops early when an update takes longer than ``--max-update-s`` (default 60)
or when ``--time-budget-s`` is spent, and says so. Writes ``scale.csv`` (and ``scale.png`` when
matplotlib is installed) to ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import platform
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_train import find_panoramas  # noqa: E402  (sun360_mini or procedural panoramas)

from findview.build import build_sampled_env  # noqa: E402
from findview.config import SimConfig, TaskConfig  # noqa: E402
from findview.dataset import EpisodeSampler, ImageEntry  # noqa: E402
from findview.sim import resolve_device  # noqa: E402
from findview.utils import atomic_write, write_text  # noqa: E402
from findview_baselines.rl.policy import build_policy  # noqa: E402
from findview_baselines.config import PPOAgentConfig  # noqa: E402
from findview_baselines.rl.ppo import PPOConfig  # noqa: E402
from findview_baselines.rl.ppo_trainer import PPOTrainer, no_distribution_validation  # noqa: E402

DEFAULT_NUM_ENVS = (16, 32, 64, 128, 256, 512, 1024)
SIZE, FOV, HIDDEN = 256, 90, 512  # the paper's setting


@dataclass(frozen=True)
class SpeedConfig:
    """One ``--configs`` entry: ``fp32`` | ``bf16`` plus ``+cl`` (channels_last) / ``+compile``."""

    precision: str = "fp32"
    channels_last: bool = False
    compile: bool = False

    @classmethod
    def parse(cls, text: str) -> "SpeedConfig":
        head, *flags = text.split("+")
        if head not in ("fp32", "bf16") or any(f not in ("cl", "compile") for f in flags):
            raise ValueError(f"--configs entry {text!r}: expected fp32 | bf16, optionally +cl and/or +compile")
        return cls(head, "cl" in flags, "compile" in flags)

    @property
    def name(self) -> str:
        return "+".join([self.precision] + ["cl"] * self.channels_last + ["compile"] * self.compile)


@dataclass
class Row:
    device: str
    config: str
    num_envs: int
    rollout_steps: int
    num_mini_batches: int
    updates: int
    steps_per_s: float
    s_per_update: float
    warmup_s: float
    env_s: float
    fwd_s: float
    other_s: float
    update_s: float
    peak_mem_gib: float
    ratio_vs_first_envs: float = float("nan")
    ratio_vs_first_config: float = float("nan")


def rollout_steps_for(n: int, device: torch.device, given: int | None) -> int:
    if given:
        return given
    return 8 if device.type == "cpu" else max(8, min(128, 65536 // n))


def measure(n: int, cfg: SpeedConfig, images: list[ImageEntry], device: torch.device, args) -> Row:
    """One warm-up update then ``args.updates`` timed ones at ``n`` environments."""
    torch.manual_seed(0)
    T = rollout_steps_for(n, device, args.rollout_steps)
    mb_cap = args.mb_samples or (512 if device.type == "cpu" else 8192)
    num_mb = min(n, max(1, math.ceil(n * T / mb_cap)))
    sim_cfg = SimConfig(fov=FOV, height=SIZE, width=SIZE, device=str(device), bank_mb=args.bank_mb)
    env = build_sampled_env(sim_cfg, TaskConfig(), EpisodeSampler(images, FOV, seed=0), n)
    env.source.level = 3
    agent = PPOAgentConfig(hidden_size=HIDDEN, precision=cfg.precision, channels_last=cfg.channels_last,
                           compile=cfg.compile)
    policy = build_policy(agent, SIZE, SIZE).to(device)
    trainer = PPOTrainer(env, policy, PPOConfig(rollout_steps=T, num_mini_batches=num_mb), total_updates=10**6, seed=0)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    try:
        with no_distribution_validation():
            t0 = time.perf_counter()
            trainer.start()
            trainer.train_update()  # warm-up: panorama decoding, grids, allocator (and compilation)
            warmup = time.perf_counter() - t0
            trainer.pop_timings()
            # too slow: report the warm-up only (not for +compile, whose warm-up is compilation)
            updates = 0 if warmup > args.max_update_s and not cfg.compile else args.updates
            start = time.perf_counter()
            for _ in range(updates):
                trainer.train_update()
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            wall = time.perf_counter() - start
    finally:
        env.close()
    t = trainer.pop_timings()
    k = max(updates, 1)
    if updates == 0:  # only the warm-up ran (an upper bound on the steady-state time)
        wall, t = warmup, {key: float("nan") for key in t}
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
    return Row(str(device), cfg.name, n, T, num_mb, updates, k * T * n / wall, wall / k, warmup,
               t["env_step"] / k, t["policy_forward"] / k, t["rollout_other"] / k, t["update"] / k, peak)


def add_ratios(rows: list[Row]) -> None:
    """Ratios against the smallest N of the same config and against the first config at the same N."""
    for r in rows:
        same_cfg = [x for x in rows if x.config == r.config]
        base = min(same_cfg, key=lambda x: x.num_envs)
        r.ratio_vs_first_envs = r.steps_per_s / base.steps_per_s
        first = next((x for x in rows if x.num_envs == r.num_envs), r)
        r.ratio_vs_first_config = r.steps_per_s / first.steps_per_s


def print_rows(rows: list[Row], header: bool = True) -> None:
    cols = f"{'config':>14} {'envs':>5} {'T':>4} {'mb':>3} | {'steps/s':>9} {'s/upd':>8} | {'env':>7} {'fwd':>7} {'other':>7} {'update':>8} | {'x envs':>6} {'x cfg':>6}"
    if header:
        print(cols)
        print("-" * len(cols))
    for r in rows:
        print(f"{r.config:>14} {r.num_envs:>5} {r.rollout_steps:>4} {r.num_mini_batches:>3} | {r.steps_per_s:>9.1f} "
              f"{r.s_per_update:>8.2f} | {r.env_s:>7.2f} {r.fwd_s:>7.2f} {r.other_s:>7.2f} {r.update_s:>8.2f} | "
              f"{r.ratio_vs_first_envs:>6.2f} {r.ratio_vs_first_config:>6.2f}", flush=True)


def write_csv(rows: list[Row], path: Path) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(asdict(rows[0])))
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in asdict(r).items()})
    write_text(path, buf.getvalue())


def write_plot(rows: list[Row], path: Path, title: str) -> bool:
    """``scale.png``: steps/s over N per config (log-log); False when matplotlib is missing."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(6, 4))
    for name in dict.fromkeys(r.config for r in rows):
        pts = [(r.num_envs, r.steps_per_s) for r in rows if r.config == name and r.updates > 0]
        if pts:
            ax.plot(*zip(*pts), marker="o", label=name)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("environments")
    ax.set_ylabel("env steps / s (incl. PPO update)")
    ax.set_title(title, fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(buf.getvalue()))
    return True


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (default cpu)")
    parser.add_argument("--num-envs", type=int, nargs="+", default=list(DEFAULT_NUM_ENVS))
    parser.add_argument("--configs", nargs="+", default=None,
                        help="fp32 | bf16 [+cl] [+compile] (default: --precision / --channels-last / --compile)")
    parser.add_argument("--precision", default="fp32", choices=("fp32", "bf16"))
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--rollout-steps", type=int, default=None, help="T (default: 8 on CPU, min(128, 65536/N) on CUDA)")
    parser.add_argument("--updates", type=int, default=2, help="timed updates after the warm-up (default 2)")
    parser.add_argument("--mb-samples", type=int, default=None, help="max samples per mini-batch (default 512 CPU, 8192 CUDA)")
    parser.add_argument("--max-update-s", type=float, default=60.0, help="stop the curve after an update this slow")
    parser.add_argument("--time-budget-s", type=float, default=float("inf"), help="start no new setting after this")
    parser.add_argument("--bank-mb", type=float, default=4096.0)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    parser.add_argument("--quick", action="store_true", help="smoke test: 64x64 views, N = 2 and 4, T = 4, 1 update")
    parser.add_argument("--out", type=Path, default=None, help="folder for scale.csv / scale.png")
    args = parser.parse_args(argv)

    global SIZE, HIDDEN
    if args.quick:
        SIZE, HIDDEN = 64, 64
        args.num_envs, args.rollout_steps, args.updates = [2, 4], args.rollout_steps or 4, 1
    device = resolve_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    configs = [SpeedConfig.parse(c) for c in args.configs] if args.configs else [
        SpeedConfig(args.precision, args.channels_last, args.compile)]
    threads = f", {torch.get_num_threads()} torch threads" if device.type == "cpu" else ""
    gpu = f" ({torch.cuda.get_device_name(device)})" if device.type == "cuda" else ""
    title = (f"PPO training throughput, {SIZE}x{SIZE} FoV {FOV} early_fusion GRU {HIDDEN}, 4 epochs; "
             f"{device}{gpu}{threads}; torch {torch.__version__}")
    print(title, f"\nPython {platform.python_version()}, {platform.processor() or platform.machine()}", flush=True)

    rows: list[Row] = []
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        images = find_panoramas(Path(tmp))
        print(f"{len(images)} panoramas; 1 warm-up + {args.updates} timed updates per setting\n", flush=True)
        print_rows([], header=True)
        stopped: dict[str, str] = {}
        for n in sorted(args.num_envs):
            for cfg in configs:
                if cfg.name in stopped:
                    continue
                if time.perf_counter() - started > args.time_budget_s:
                    stopped[cfg.name] = f"time budget of {args.time_budget_s:g} s spent before N={n}"
                    continue
                try:
                    row = measure(n, cfg, images, device, args)
                except torch.OutOfMemoryError:
                    stopped[cfg.name] = f"out of device memory at N={n}"
                    torch.cuda.empty_cache()
                    continue
                rows.append(row)
                add_ratios(rows)
                print_rows([row], header=False)
                if row.updates == 0 or row.s_per_update > args.max_update_s:
                    stopped[cfg.name] = (f"stopped after N={n}: an update took {row.s_per_update:.0f} s "
                                         f"(> --max-update-s {args.max_update_s:g})")
    if not rows:
        print("nothing measured")
        return rows
    add_ratios(rows)
    print("\nAll settings (x envs: steps/s against the smallest N of the config; x cfg: against the first config at that N)")
    print_rows(rows)
    for name, why in stopped.items():
        print(f"{name}: {why}")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_csv(rows, args.out / "scale.csv")
        png = write_plot(rows, args.out / "scale.png", title)
        print(f"wrote {args.out / 'scale.csv'}" + (f" and {args.out / 'scale.png'}" if png else " (no matplotlib: no PNG)"))
    return rows


if __name__ == "__main__":
    main()
