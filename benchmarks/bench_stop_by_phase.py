"""What ``agent.stop_by_phase`` costs a learned agent per step, against the same agent without it, in the same run.

    python benchmarks/bench_stop_by_phase.py [--checkpoint pretrained/findview_sun360mini_indoor_robust.pth]
        [--slots 16] [--size 256] [--steps 100] [--threads 1] [--device cpu]

The agent acts on random views and targets (``--size`` pixels square; the network averages them down to its own
size), so its STOP probability stays below 0.1 and every slot measures phase correlation every step: the option's
worst case. Prints ms per ``act`` (median of ``--steps`` calls after 5 warm-up calls) with the option off (the
reference) and on, and their ratio; figures go to benchmarks/RESULTS.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from findview.episode import Episode
from findview_baselines.agents.ppo_agent import PPOAgent
from findview_baselines.agents.stop_refine import StopRefiner


def ms_per_act(checkpoint: str, slots: int, size: int, steps: int, device: str, phase: bool) -> float:
    """Median milliseconds of one ``act`` of ``slots`` slots on ``size``-pixel views."""
    agent = PPOAgent.from_checkpoint(
        checkpoint, slots, device, height=size, width=size, refiner=StopRefiner(slots, 90.0), fov=90.0,
        stop_by=100_000, stop_by_phase=phase,
    )
    episodes = [Episode(f"e{i}", "x.jpg", 0, 0, 0, 10, difficulty="easy", seed=i) for i in range(slots)]
    agent.reset(list(range(slots)), episodes)
    gen = torch.Generator().manual_seed(0)
    frames = [torch.randint(0, 256, (slots, 3, size, size), dtype=torch.uint8, generator=gen)
              .contiguous(memory_format=torch.channels_last).to(device) for _ in range(4)]
    target = frames[0]
    times = []
    for k in range(steps + 5):
        obs = {"view": frames[1 + k % 3], "target": target}
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        agent.act(obs)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        if k >= 5:
            times.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="pretrained/findview_sun360mini_indoor_robust.pth")
    ap.add_argument("--slots", type=int, default=16)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    off = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, phase=False)
    on = ms_per_act(args.checkpoint, args.slots, args.size, args.steps, args.device, phase=True)
    print(f"{args.slots} slots, {args.size}x{args.size} views, {args.threads} thread(s), {args.device}")
    print("| agent.stop_by_phase | ms per act | ratio |")
    print("|---|---|---|")
    print(f"| off (reference) | {off:.1f} | 1.00 |")
    print(f"| on | {on:.1f} | {on / off:.2f} |")


if __name__ == "__main__":
    main()
