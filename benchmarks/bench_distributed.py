"""DD-PPO scaling on CPU: env steps per second of 1 process vs K gloo processes (``trainer.distributed``).

    python benchmarks/bench_distributed.py                     # 1 vs 2 processes, 8 envs per process
    python benchmarks/bench_distributed.py --procs 1 2 4 --updates 6 --size 64 --envs 8

Every run is the real training loop (``findview_baselines.training.train``) on the synthetic data set
(procedural panoramas made once under ``--data``), with ``--envs`` environments *per process*, the
paper's early-fusion network (GRU ``--hidden``), ``--rollout-steps`` steps per update, 4 PPO epochs and no
validation. K processes are started like torchrun starts them (``env://`` variables, gloo); one process
runs without torch.distributed. Throughput = env steps of all processes per second of wall-clock time
between the end of the first (warm-up) update and the end of the last one. Scaling efficiency =
throughput(K) / (K x throughput(1)); the ideal is 1.0 when every process has a core of its own.

Each process uses one torch thread. On a machine with fewer free cores than processes the efficiency
says more about the machine than about the algorithm: state the core count and the load with the
numbers (the script prints both).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _overrides(args: argparse.Namespace, data: Path, world: int) -> list[str]:
    return [
        "dataset=synthetic", f"dataset.root={data / 'images'}", f"dataset.out_dir={data / 'out'}",
        "dataset.num_images=16", "dataset.width=512",
        f"sim.height={args.size}", f"sim.width={args.size}", "sim.device=cpu", "sim.prefetch_workers=0",
        f"agent.hidden_size={args.hidden}", f"trainer.ppo.rollout_steps={args.rollout_steps}", "trainer.ppo.ppo_epochs=4",
        f"trainer.num_envs={args.envs}", f"trainer.num_updates={args.updates}", "trainer.val_interval=0",
        "trainer.val_at_end=false", "trainer.checkpoint_interval=0", "trainer.log_interval=1000",
        "trainer.progress=false", "trainer.torch_threads=1", "trainer.resume=false",
        f"trainer.distributed={'true' if world > 1 else 'false'}",
    ]


def _worker(rank: int, world: int, port: int, args: argparse.Namespace, data: Path, out: Path) -> None:
    import torch

    os.environ.update(OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    if world > 1:
        os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank),
                          WORLD_SIZE=str(world), LOCAL_RANK=str(rank))
    import findview_baselines.training.run as run
    from findview_baselines.cli import compose_config

    stamps: list[float] = []

    class Clock(run.Callback):
        def on_update(self, ctx: Any, stats: Any) -> None:
            stamps.append(time.perf_counter())

    learn = run.learn
    run.learn = lambda ctx, callbacks, stop: learn(ctx, [Clock(), *callbacks], stop)
    cfg = compose_config("train", _overrides(args, data, world))
    result = run.train(cfg, out / f"run_{world}")
    if rank == 0:
        steps = (len(stamps) - 1) * args.rollout_steps * args.envs * world
        (out / f"result_{world}.json").write_text(json.dumps(
            {"procs": world, "updates_timed": len(stamps) - 1, "env_steps": steps,
             "seconds": stamps[-1] - stamps[0], "steps_per_s": steps / (stamps[-1] - stamps[0]),
             "session_steps_per_s": result.steps_per_second}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--procs", type=int, nargs="+", default=[1, 2], help="process counts to compare")
    parser.add_argument("--envs", type=int, default=8, help="environments per process")
    parser.add_argument("--size", type=int, default=64, help="view size in pixels (square)")
    parser.add_argument("--hidden", type=int, default=512, help="GRU size")
    parser.add_argument("--rollout-steps", type=int, default=32, help="steps per environment per update")
    parser.add_argument("--updates", type=int, default=5, help="updates per run (the first is warm-up)")
    parser.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "findview_bench_distributed",
                        help="where the synthetic panoramas are made (reused)")
    args = parser.parse_args()
    if args.updates < 2:
        parser.error("--updates must be at least 2 (the first one is warm-up)")

    import findview  # noqa: F401  (thread policy before torch)
    import torch.multiprocessing as mp

    sys.path.insert(0, str(REPO))
    out = Path(tempfile.mkdtemp(prefix="bench_distributed_"))
    print(f"cores: {os.cpu_count()}, load average before: {os.getloadavg()[0]:.2f}; {args.envs} envs/process, "
          f"{args.size}x{args.size}, GRU {args.hidden}, {args.rollout_steps} steps/update, "
          f"{args.updates - 1} timed updates")
    results = {}
    for world in args.procs:
        mp.start_processes(_worker, args=(world, _free_port(), args, args.data, out), nprocs=world, join=True,
                           start_method="spawn")
        results[world] = json.loads((out / f"result_{world}.json").read_text())
        r = results[world]
        print(f"{world} process(es): {r['env_steps']} env steps in {r['seconds']:.1f} s = {r['steps_per_s']:.0f} "
              f"steps/s (whole session incl. warm-up: {r['session_steps_per_s']:.0f})", flush=True)
    base = results.get(1)
    if base is not None:
        for world, r in results.items():
            if world > 1:
                ratio = r["steps_per_s"] / base["steps_per_s"]
                print(f"{world} vs 1: throughput x{ratio:.2f}, scaling efficiency {ratio / world:.0%}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
