#!/usr/bin/env python
"""Compare stop-offset nets (``agent.refine_model`` files) on the same rendered pairs.

Usage::

    python tools/report_stop_offsets.py --splits data/sun360_mini_indoor/splits.json --root <sun360_mini> \\
        --models pretrained/stop_offsets_fov60_256.pth outputs/stop_offsets/other.pth --far-lookalike 32 \\
        --min-near 0.5 0.99

The pairs are those ``tools/train_stop_offsets.py --seed S`` reports on (``--pairs`` of them from the ``--split``
panoramas, default val; the same ``--far-fraction`` / ``--far-lookalike`` settings give the same pairs), rendered
once at the FoV and view size of the models (they must share both). For each model and each ``--min-near`` bar it
prints, per corruption and over all pairs (``all``): ``stay`` (views on their target left alone), ``one_off``
(views one degree off moved towards it first) and, for nets with the near output, ``keep`` (views at most 2
degrees off kept) and ``refuse`` (far views refused); the columns of
:func:`findview_baselines.training.stop_offsets.accuracy`. ``--far-lookalike k`` makes the far views put anywhere
the most alike of k poses, the look-alikes a stop check must refuse. Bad input prints one line and exits with
status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from findview.dataset.splits import MissingDataFile  # noqa: E402
from findview_baselines.agents.stop_offsets import StopOffsetsError, load_stop_offsets  # noqa: E402
from findview_baselines.training.stop_offsets import accuracy, pooled_panoramas, sample_pairs  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Parse, load, sample, report; returns the exit status (0, or 2 for bad input)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--splits", required=True, nargs="+",
                   help="splits.json of tools/make_dataset.py; several files pool their panoramas")
    p.add_argument("--root", required=True, help="the panorama folder the splits name their images under")
    p.add_argument("--models", required=True, nargs="+", help="stop-offset net files (same FoV and view size)")
    p.add_argument("--split", default="val", help="the split whose panoramas give the pairs (default val)")
    p.add_argument("--pairs", type=int, default=3000, help="pairs rendered (default 3000, the training's val pairs)")
    p.add_argument("--far-fraction", type=float, default=0.25, help="share of far views (default 0.25)")
    p.add_argument("--far-lookalike", type=int, default=1,
                   help="each far view put anywhere is the most alike of this many random poses (default 1)")
    p.add_argument("--min-stay", type=float, default=0.3, help="the refinement's threshold (agent.refine_min_stay)")
    p.add_argument("--min-near", type=float, nargs="+", default=[0.5],
                   help="near-probability bars for keep / refuse (agent.refine_min_near, agent.stop_near_min_near)")
    p.add_argument("--seed", type=int, default=0, help="the training's --seed whose val pairs to render (default 0)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = p.parse_args(argv)
    if (args.pairs < 1 or not 0 <= args.far_fraction < 1 or args.far_lookalike < 1
            or not all(0 < n < 1 for n in args.min_near)):
        print(f"report_stop_offsets: expected positive --pairs (got {args.pairs}), --far-fraction in [0, 1) (got "
              f"{args.far_fraction}), --far-lookalike >= 1 (got {args.far_lookalike}) and --min-near bars in (0, 1) "
              f"(got {args.min_near})", file=sys.stderr)
        return 2
    torch.set_num_threads(args.threads)
    try:
        nets = [load_stop_offsets(m) for m in args.models]
        first = nets[0]
        for path, net in zip(args.models[1:], nets[1:]):
            if abs(net.fov - first.fov) > 1e-6 or net.size != first.size:
                raise StopOffsetsError(f"{path}: made for FoV {net.fov:g} and {net.size}x{net.size} views, "
                                       f"{args.models[0]} for FoV {first.fov:g} and {first.size}x{first.size}")
        panoramas = pooled_panoramas(args.splits, Path(args.root), args.split)
    except (ValueError, MissingDataFile) as err:  # StopOffsetsError, PanoramaError and DatasetError are ValueErrors
        print(f"report_stop_offsets: {err}", file=sys.stderr)
        return 2
    start = time.time()
    print(f"{len(panoramas)} {args.split} panoramas; rendering {args.pairs} pairs at FoV {first.fov:g}, "
          f"{first.size}x{first.size} (seed {args.seed} + 2, far {args.far_fraction}, look-alike of "
          f"{args.far_lookalike})", flush=True)
    pairs = sample_pairs(panoramas, args.pairs, first.fov, first.size, args.seed + 2, progress=True,
                         far_fraction=args.far_fraction, lookalike=args.far_lookalike)
    with torch.no_grad():
        for path, net in zip(args.models, nets):
            for bar in args.min_near:
                report = accuracy(net, pairs, args.min_stay, bar)
                columns = ["stay", "one_off"] + (["keep", "refuse"] if net.near else [])
                print(f"\n{path}" + (f", min_near {bar:g}" if net.near else ""))
                print(f"{'pairs':18s} {'n':>5s}" + "".join(f" {c:>8s}" for c in columns))
                for name, r in report.items():
                    print(f"{name:18s} {r['pairs']:5d}" + "".join(f" {r[c]:8.3f}" for c in columns))
                if not net.near:
                    break  # the bars change nothing without the near output
    print(f"\n({time.time() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
