"""Shared by the per-step cost benchmarks of learned-agent options (bench_stop_by_phase.py, bench_mirror.py): their
command-line options and the timing of ``agent.act`` on random views."""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from findview.episode import Episode


def act_options(doc: str) -> argparse.Namespace:
    """Parse ``--checkpoint --slots --size --steps --threads --device`` (``doc``: the script's help) and set torch's
    CPU threads."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default="pretrained/findview_sun360mini_indoor_robust.pth")
    ap.add_argument("--slots", type=int, default=16)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    return args


def median_act_ms(agent, slots: int, size: int, steps: int, device: str) -> float:  # noqa: ANN001
    """Median milliseconds of one ``agent.act`` of ``slots`` slots on random ``size``-pixel views and targets, over
    ``steps`` calls after 5 warm-up calls; a slot that stops starts a new episode, so every slot acts every call."""
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
        actions = agent.act(obs)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        if k >= 5:
            times.append(time.perf_counter() - t)
        stopped = np.flatnonzero(actions.cpu().numpy() == 4)
        if len(stopped):
            agent.reset(stopped.tolist(), [episodes[i] for i in stopped])
    return 1000.0 * float(np.median(times))
