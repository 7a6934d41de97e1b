"""Which cue says "the target is in view" at a given offset? The pitch-warped phase peak and the wide match's peak.

A scripted search that forces moves (a sweep of a search row, say) must hand the moves back to the network where
the target shows. This measures, on the targets of an episode file (use a val file: tune on val), how two
parameter-free cues of the robust agents respond to a view at a fixed offset from the target:

- the best peak of the pitch-warped phase correlation (``PitchWarpedPhase``, ``agent.pitch_warps``; z-scores / 10),
- the wide match's peak (``WideMatch``, ``agent.wide_match``: the best ZNCC of view and target over their overlap).

For every ``--stride``-th episode and every (pitch, yaw) offset in ``OFFSETS`` (degrees; the signs drawn at random,
the view's pitch clamped to +-60) it renders view and target at 256x256, averages them to 64x64 (the robust agents'
setting), and prints per offset the median, 90th percentile and maximum of each cue and the share of views at or
above ``--bars``. Clean targets (the cue's best case; corrupt them in the agent's own evaluation).

    python benchmarks/inview_cue.py --episodes data/sun360_mini_indoor_e40/episodes/val_fov90.json \
        --root $FINDVIEW_SUN360_MINI
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from findview.imageio import load_panorama  # noqa: E402
from findview.sim.equi2pers import equi2pers  # noqa: E402
from findview_baselines.rl.pitch_warps import WARP_FRACTIONS, PitchWarpedPhase  # noqa: E402
from findview_baselines.rl.wide_match import WIDE_PEAK, WideMatch  # noqa: E402

#: (pitch, yaw) offsets of the view from the target, degrees (magnitudes; signs drawn per episode)
OFFSETS = ((0, 0), (0, 10), (0, 20), (0, 30), (0, 45), (0, 60), (0, 75), (0, 90), (0, 135), (0, 180),
           (15, 0), (30, 0), (45, 0), (60, 0), (30, 30), (45, 45), (30, 90), (45, 180))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", required=True, help="an episode file of tools/make_dataset.py (a val split)")
    parser.add_argument("--root", required=True, help="the panorama folder the episode file names its images under")
    parser.add_argument("--stride", type=int, default=3, help="every n-th episode (default 3)")
    parser.add_argument("--bars", type=float, nargs="+", default=[2.0, 2.5], help="warp-peak bars to count")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if not Path(args.episodes).is_file():
        parser.error(f"--episodes {args.episodes}: no such episode file (tools/make_dataset.py writes them)")
    if args.stride < 1:
        parser.error(f"--stride must be >= 1 episodes, got {args.stride}")
    torch.set_num_threads(1)
    data = json.loads(Path(args.episodes).read_text())
    episodes = data["episodes"][::args.stride]
    fov = float(data["fov"])
    warps, wide = PitchWarpedPhase(64, 64, fov), WideMatch(64, 64)
    rng = np.random.default_rng(args.seed)
    panos: dict[str, torch.Tensor] = {}

    def render(image: str, pitch: float, yaw: float) -> torch.Tensor:
        if image not in panos:
            panos[image] = torch.from_numpy(load_panorama(Path(args.root) / image)).permute(2, 0, 1)[None].contiguous()
        view = equi2pers(panos[image], torch.tensor([float(pitch)]), torch.tensor([float(yaw)]), fov, 256, 256)
        return F.avg_pool2d(view.float() / 255, 4)

    warp_peaks = {o: [] for o in OFFSETS}
    wide_peaks = {o: [] for o in OFFSETS}
    for e in episodes:
        target = render(e["image"], e["target_pitch"], e["target_yaw"])
        for dp, dy in OFFSETS:
            pitch = float(np.clip(e["target_pitch"] + rng.choice([-1, 1]) * dp, -60, 60))
            view = render(e["image"], pitch, e["target_yaw"] + rng.choice([-1, 1]) * dy)
            with torch.no_grad():
                warp_peaks[(dp, dy)].append(float(warps(view, target)[0, :len(WARP_FRACTIONS)].max()))
                wide_peaks[(dp, dy)].append(float(wide(view, target)[0, WIDE_PEAK]))
    print(f"{len(episodes)} targets of {args.episodes} (FoV {fov:g}), clean; per offset: median / p90 / max")
    bars = " ".join(f">={b:g}" for b in args.bars)
    print(f"{'pitch':>5} {'yaw':>4} | {'warp peak':>18} {bars} | {'wide peak':>18}")
    for o in OFFSETS:
        w, z = np.array(warp_peaks[o]), np.array(wide_peaks[o])
        shares = " ".join(f"{np.mean(w >= b):>{len(f'>={b:g}')}.2f}" for b in args.bars)
        print(f"{o[0]:>5} {o[1]:>4} | {np.median(w):5.2f} / {np.quantile(w, 0.9):4.2f} / {w.max():4.2f} {shares} | "
              f"{np.median(z):5.2f} / {np.quantile(z, 0.9):4.2f} / {z.max():4.2f}")


if __name__ == "__main__":
    main()
