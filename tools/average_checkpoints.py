#!/usr/bin/env python
"""Average the policy weights of two or more checkpoints of one network into one checkpoint (a "model soup"), or
copy one checkpoint's weights without its resume state (a file to ship).

Usage::

    python tools/average_checkpoints.py RUN_A/checkpoints/val_u00500.pth RUN_B/checkpoints/val_u00500.pth \\
        --out soup.pth

For runs fine-tuned from one common checkpoint (the same network and starting weights; e.g. two stage-3 runs of
the robust recipe, ``configs/experiment/robust_polish.yaml``): every float tensor of the policy becomes the mean
of the inputs' (:func:`findview_baselines.rl.checkpoint.average_checkpoints`). The output keeps the first input's
signature and config (so ``tools/eval.py checkpoint=soup.pth`` evaluates it like the inputs), carries no
validation metrics and no resume state, and lists its inputs under ``averaged_from``. Whether a soup is better
than its inputs is for the val sets to say: evaluate it before use.

The file is written atomically; an existing ``--out`` is replaced only with ``--overwrite``. Bad input (a
missing file, not a findview checkpoint, checkpoints of different networks) prints one line and exits with
status 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from findview_baselines.rl.checkpoint import (  # noqa: E402
    CheckpointError,
    CheckpointNotFound,
    average_checkpoints,
    save_checkpoint,
)


def main(argv: list[str] | None = None) -> int:
    """Parse the command line, average, write; returns the exit status (0, or 2 for bad input)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("inputs", nargs="+", help="checkpoint files (.pth written by tools/train.py); one: a copy without the resume state")
    p.add_argument("--out", required=True, help="the averaged checkpoint to write")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    args = p.parse_args(argv)
    out = Path(args.out)
    if any(Path(i).resolve() == out.resolve() for i in args.inputs):
        print(f"average_checkpoints: --out {out} is one of the inputs; expected a new file", file=sys.stderr)
        return 2
    if out.exists() and not args.overwrite:
        print(f"average_checkpoints: {out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    try:
        state = average_checkpoints(args.inputs)
    except (CheckpointError, CheckpointNotFound, ValueError) as err:
        print(f"average_checkpoints: {err}", file=sys.stderr)
        return 2
    save_checkpoint(out, state)  # atomic; makes the folder
    print(f"averaged {len(args.inputs)} checkpoints -> {out}" if len(args.inputs) > 1 else f"copied the weights -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
