#!/usr/bin/env python
"""Train a stop-offset net: the learned check of a learned agent's stop under corruption (``agent.refine_model``).

Usage::

    python tools/train_stop_offsets.py --splits data/sun360_mini_indoor/splits.json --root <sun360_mini> \\
        --out pretrained/stop_offsets_fov90_256.pth

Pairs of a target (corrupted: every corruption, severity 1-5, 20% clean) and a view a few degrees from it are
rendered from the **train** panoramas of ``--splits`` (one splits file or several, pooled; ``--pairs`` of them,
plus ``--blur-pairs`` with the corruptions of ``--blur-corruptions`` only: those whose content moves the most),
and the net learns the view's offset per axis (findview_baselines/agents/stop_offsets.py). A ``--far-fraction`` of
the pairs (and of the val pairs) put the view elsewhere on the panorama instead, so that the net also learns
whether a view is near its target at all (the near output ``agent.refine_min_near`` uses to refuse stops on
look-alike views); with
``--far-lookalike k`` each such view put anywhere is the most alike of k random poses (the look-alikes themselves).
``--val-pairs`` pairs from the **val** panoramas report how often a view on its target is left alone and how often
a view one degree off is sent the right way, and with the near output how often a view at most 2 degrees off is
kept and a far one refused, per corruption (the
``stay`` / ``one_off`` / ``keep`` / ``refuse`` of findview_baselines/training/stop_offsets.py, ``accuracy``); they
are stored in the file with the command's settings (``tools/report_stop_offsets.py`` scores other nets on the same
pairs). The file is written atomically; an existing ``--out`` is
replaced only with ``--overwrite``. Bad input prints one line and exits with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from findview.corruptions import NAMES  # noqa: E402
from findview.dataset.splits import MissingDataFile  # noqa: E402
from findview_baselines.agents.stop_offsets import save_stop_offsets  # noqa: E402
from findview_baselines.training.stop_offsets import (  # noqa: E402
    Pairs,
    accuracy,
    fit,
    pooled_panoramas,
    sample_pairs,
)


def main(argv: list[str] | None = None) -> int:
    """Parse, sample, train, report, write; returns the exit status (0, or 2 for bad input)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--splits", required=True, nargs="+",
                   help="splits.json of tools/make_dataset.py (train and val panoramas); several files pool their "
                        "panoramas (e.g. the indoor and the outdoor ones)")
    p.add_argument("--root", required=True, help="the panorama folder the splits name their images under")
    p.add_argument("--out", required=True, help="the .pth to write")
    p.add_argument("--fov", type=float, default=90.0, help="field of view of the views, degrees (default 90)")
    p.add_argument("--size", type=int, default=256, help="view side, pixels (default 256)")
    p.add_argument("--pairs", type=int, default=32000, help="training pairs, every corruption (default 32000)")
    p.add_argument("--far-fraction", type=float, default=0.25,
                   help="share of --pairs and --val-pairs whose view is far from the target, for the near output "
                        "(agent.refine_min_near); 0: a net without it (default 0.25)")
    p.add_argument("--far-lookalike", type=int, default=1,
                   help="each far view put anywhere on the panorama is the most alike of this many random poses (the "
                        "look-alikes the near output must refuse); 1: a random pose (default 1)")
    p.add_argument("--blur-pairs", type=int, default=10000, help="more training pairs, --blur-corruptions only (default 10000)")
    p.add_argument("--blur-corruptions", default="motion_blur,glass_blur", help="comma-separated corruption names")
    p.add_argument("--val-pairs", type=int, default=3000, help="val pairs for the report (default 3000)")
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--min-stay", type=float, default=0.3, help="the refinement's threshold the report uses (agent.refine_min_stay)")
    p.add_argument("--min-near", type=float, default=0.5,
                   help="the stop check's threshold the report uses (agent.refine_min_near)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    out = Path(args.out)
    if out.exists() and not args.overwrite:
        print(f"train_stop_offsets: {out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    blur = [c for c in args.blur_corruptions.split(",") if c]
    bad = [c for c in blur if c not in NAMES]
    if (bad or args.size < 142 or args.pairs < 1 or args.val_pairs < 1 or not 0 <= args.far_fraction < 1
            or args.far_lookalike < 1):
        print(f"train_stop_offsets: expected corruption names from {', '.join(NAMES)} (got {bad}), --size >= 142 "
              f"pixels, positive --pairs / --val-pairs, --far-fraction in [0, 1) (got {args.far_fraction}) and "
              f"--far-lookalike >= 1 (got {args.far_lookalike})", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    start = time.time()
    try:
        train_panos = pooled_panoramas(args.splits, Path(args.root), "train")
        val_panos = pooled_panoramas(args.splits, Path(args.root), "val")
    except (ValueError, MissingDataFile) as err:  # PanoramaError and DatasetError are ValueErrors
        print(f"train_stop_offsets: {err}", file=sys.stderr)
        return 2
    print(f"{len(train_panos)} train and {len(val_panos)} val panoramas; sampling pairs", flush=True)
    far = args.far_fraction
    alike = args.far_lookalike
    parts = [sample_pairs(train_panos, args.pairs, args.fov, args.size, args.seed, progress=True, far_fraction=far,
                          lookalike=alike)]
    if args.blur_pairs and blur:
        parts.append(sample_pairs(train_panos, args.blur_pairs, args.fov, args.size, args.seed + 1, blur, progress=True))
    val = sample_pairs(val_panos, args.val_pairs, args.fov, args.size, args.seed + 2, progress=True, far_fraction=far,
                       lookalike=alike)
    net = fit(Pairs.cat(parts), args.fov, args.size, args.epochs, args.seed)
    report = accuracy(net, val, args.min_stay, args.min_near)
    columns = ["stay", "one_off"] + (["keep", "refuse"] if net.near else [])
    print(f"{'val pairs':18s}" + "".join(f" {c:>8s}" for c in columns))
    for name, r in report.items():
        print(f"{name:18s}" + "".join(f" {r[c]:8.3f}" for c in columns))
    meta = {"command": " ".join(sys.argv), "splits": " ".join(args.splits), "pairs": args.pairs, "far_fraction": far,
            "far_lookalike": alike, "min_near": args.min_near,
            "blur_pairs": args.blur_pairs, "blur_corruptions": blur, "epochs": args.epochs, "seed": args.seed,
            "min_stay": args.min_stay, "val": report, "seconds": round(time.time() - start, 1)}
    save_stop_offsets(out, net, meta)
    print(f"wrote {out} ({meta['seconds']} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
