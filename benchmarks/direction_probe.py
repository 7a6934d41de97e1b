"""Which way does a learned agent turn first, for a target partly in view to its left?

A diagnostic of how far to the side a learned agent still sees a clean target: episodes start with the target
``|dyaw|`` = 10..70 degrees to the **left** and ``|dpitch|`` = 0..30 above or below (random start poses on the
panoramas of one split), and the agent acts once from a fresh state (its checkpoint's search settings). A first
move towards the target (LEFT, or the pitch move towards it) is right; an agent that does not see the target pans
right, its search. Prints the share of right first moves per ``(|dpitch|, |dyaw|)``. Targets to the left only:
to the right, panning (the search) and turning towards the target are the same move.

    python benchmarks/direction_probe.py --checkpoint pretrained/findview_sun360mini_indoor_robust.pth \\
        --splits data/sun360_mini_indoor/splits.json --root $FINDVIEW_SUN360_MINI --split val
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from findview.build import build_static_env  # noqa: E402
from findview.config import SimConfig, TaskConfig  # noqa: E402
from findview.episode import Episode  # noqa: E402
from findview.task.actions import Action  # noqa: E402
from findview_baselines.agents.ppo_agent import PPOAgent  # noqa: E402

YAW_OFFSETS = (10, 20, 30, 40, 50, 60, 70)  # degrees to the left
PITCH_OFFSETS = (0, 10, 20, 30)  # degrees above or below


def probe_episodes(images: list[str], per_cell: int, fov: float, seed: int) -> list[tuple[Episode, int, int, int]]:
    """``(episode, |dyaw|, |dpitch|, pitch sign)`` with the target ``|dyaw|`` to the left of a random start."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(per_cell):
        for dy in YAW_OFFSETS:
            for dp in PITCH_OFFSETS:
                p0, y0 = int(rng.integers(-35, 36)), int(rng.integers(-179, 181))
                sign = 1 if rng.random() < 0.5 else -1
                tp = p0 + sign * dp
                if abs(tp) > 60:
                    sign, tp = -sign, p0 - sign * dp
                ty = (y0 - dy + 180) % 360 - 180
                ty = 180 if ty == -180 else ty  # yaw in (-180, 180]
                ep = Episode(f"probe-{len(out)}", images[k % len(images)], p0, y0, tp, ty)
                out.append((ep, dy, dp, sign))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True, help="a learned agent's .pth")
    ap.add_argument("--splits", required=True, help="splits.json of tools/make_dataset.py")
    ap.add_argument("--root", required=True, help="the panorama folder the splits name their images under")
    ap.add_argument("--split", default="val", choices=("train", "val"), help="panoramas used (default val; never test)")
    ap.add_argument("--fov", type=float, default=90.0, help="field of view, degrees (default 90)")
    ap.add_argument("--size", type=int, default=256, help="rendered view size, pixels (default 256, averaged down)")
    ap.add_argument("--per-cell", type=int, default=40, help="episodes per (dpitch, dyaw) cell (default 40)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    entries = json.loads(Path(args.splits).read_text())["splits"][args.split]
    if not entries:
        ap.error(f"{args.splits}: no {args.split} split")
    images = [str(Path(args.root) / e["image"]) for e in entries]
    probes = probe_episodes(images, args.per_cell, args.fov, args.seed)
    n = len(probes)
    env = build_static_env(SimConfig(fov=args.fov, height=args.size, width=args.size), TaskConfig(),
                           [p[0] for p in probes], n)
    obs = env.reset()
    agent = PPOAgent.from_checkpoint(args.checkpoint, n, height=args.size, width=args.size, fov=args.fov)
    agent.reset(list(range(n)), env.episodes)
    first = agent.act(obs).tolist()
    right: dict[tuple[int, int], list[bool]] = {}
    for (_, dy, dp, sign), action in zip(probes, first):
        good = {int(Action.LEFT)} | ({int(Action.UP) if sign > 0 else int(Action.DOWN)} if dp else set())
        right.setdefault((dp, dy), []).append(action in good)
    print(f"{args.checkpoint}, {args.split} panoramas, FoV {args.fov:g}: first moves towards a target to the left (%)")
    print("| dpitch \\ dyaw | " + " | ".join(str(d) for d in YAW_OFFSETS) + " |")
    print("|---" * (len(YAW_OFFSETS) + 1) + "|")
    for dp in PITCH_OFFSETS:
        print(f"| {dp} | " + " | ".join(f"{100 * np.mean(right[(dp, dy)]):.0f}" for dy in YAW_OFFSETS) + " |")
    print(f"all: {100 * np.mean([v for cell in right.values() for v in cell]):.1f}% of {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
