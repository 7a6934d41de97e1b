"""How well does a phase-correlation peak tell a target straight above / below the view from an unrelated one?

The plain peak (``PhaseCorrelation``, what the ``phase`` policy reads) against the best peak of the pitch-warped
phase correlation (``PitchWarpedPhase``, ``agent.pitch_warps``), on pairs rendered from the training panoramas of a
data set (never its val / test panoramas): "related" pairs have the target 20-45 degrees above or below the view
and up to 40 degrees to either side (in view, partly: what the agent passes on a search row), "unrelated" ones
120-240 degrees away. Views are rendered at 256x256 and averaged to 64x64 (the robust agents' setting); the target
is corrupted at 256x256, as in the robustness benchmark. Prints per corruption the AUC of each peak (the chance
that a related pair reads higher than an unrelated one) and how often the best hypothesis has the right sign.

    python benchmarks/pitch_warp_cue.py --splits data/sun360_mini_indoor/splits.json --root $FINDVIEW_SUN360_MINI \
        --corruptions none fog spatter glass_blur snow
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

from findview.corruptions import corrupt  # noqa: E402
from findview.imageio import load_panorama  # noqa: E402
from findview.sim.equi2pers import equi2pers  # noqa: E402
from findview_baselines.rl.encoders import PhaseCorrelation, standardize  # noqa: E402
from findview_baselines.rl.pitch_warps import WARP_FRACTIONS, PitchWarpedPhase  # noqa: E402

K = len(WARP_FRACTIONS)


def auc(related: np.ndarray, unrelated: np.ndarray) -> float:
    """P(a related pair's value > an unrelated pair's), over all pairs of pairs."""
    return float((related[:, None] > unrelated[None, :]).mean())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--splits", required=True, help="splits.json of tools/make_dataset.py (its train split is used)")
    ap.add_argument("--root", required=True, help="the panorama folder the splits name their images under")
    ap.add_argument("--corruptions", nargs="+", default=["none"], help="corruption names (severity 3), or none")
    ap.add_argument("--pairs", type=int, default=160, help="pairs per corruption, half related (default 160)")
    ap.add_argument("--panoramas", type=int, default=8, help="training panoramas used (default 8)")
    ap.add_argument("--fov", type=float, default=90.0, help="field of view, degrees (default 90)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    train = json.loads(Path(args.splits).read_text())["splits"]["train"][: args.panoramas]
    if not train:
        ap.error(f"{args.splits}: no train split")
    panos = [torch.from_numpy(load_panorama(Path(args.root) / e["image"])).permute(2, 0, 1)[None] for e in train]
    plain_pc = PhaseCorrelation(64, 64, 8, 6)
    warps = PitchWarpedPhase(64, 64, args.fov)

    def render(pano: torch.Tensor, pitch: int, yaw: int, corruption: str = "none", seed: int = 0) -> torch.Tensor:
        view = equi2pers(pano, torch.tensor([float(pitch)]), torch.tensor([float(yaw)]), args.fov, 256, 256)
        if corruption != "none":
            view = corrupt(view, corruption, 3, generator=torch.Generator().manual_seed(seed))
        return F.avg_pool2d(view.float() / 255, 4)

    print(f"| corruption (severity 3) | AUC plain peak | AUC best warped peak | best hypothesis of the right sign |")
    print("|---|---|---|---|")
    for corruption in args.corruptions:
        rng = np.random.default_rng(0)
        plain = {0: [], 1: []}
        warped = {0: [], 1: []}
        sign_right = []
        for trial in range(args.pairs):
            pano = panos[trial % len(panos)]
            pitch, yaw = int(rng.integers(-30, 31)), int(rng.integers(-180, 180))
            related = trial % 2 == 0
            if related:
                dp = int(rng.integers(20, 46)) * (1 if rng.random() < 0.5 else -1)
                dy = int(rng.integers(-40, 41))
            else:
                dp, dy = int(rng.integers(-60, 61)), int(rng.integers(120, 241))
            target_pitch = max(-60, min(60, pitch + dp))
            view = render(pano, pitch, yaw)
            target = render(pano, target_pitch, yaw + dy, corruption, trial)
            grey = lambda x: standardize(x).mean(dim=1, keepdim=True)  # noqa: E731
            p = float(plain_pc(grey(view), grey(target))[1][0, 0])
            w = warps(view, target)[0, :K]
            kind = 0 if related else 1
            plain[kind].append(p)
            warped[kind].append(float(w.max()))
            if related:
                sign_right.append(np.sign(WARP_FRACTIONS[int(w.argmax())]) == np.sign(target_pitch - pitch))
        print(f"| {corruption} | {auc(np.array(plain[0]), np.array(plain[1])):.3f} | "
              f"{auc(np.array(warped[0]), np.array(warped[1])):.3f} | {100 * np.mean(sign_right):.1f}% |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
