#!/usr/bin/env python
"""Evaluate an agent on the static episodes of a data set split (Hydra; config ``configs/eval.yaml``).

Examples::

    python tools/eval.py agent=orb                                  # synthetic data set, test split
    python tools/eval.py agent=sift dataset=folder dataset.root=<dir> dataset.out_dir=<dir> split=test
    python tools/eval.py agent=ppo checkpoint=<run>/checkpoints/best.pth difficulty=hard
    python tools/eval.py agent=oracle episodes=<episode file> video=2
    python tools/eval.py -m agent=sift agent.d_thresh=10,20,30,40,50,60,70,80,90,100,inf split=val difficulty=easy

The run folder (``hydra.run.dir``) receives ``episodes.jsonl`` (one record per episode), ``summary.json``
(``{difficulty: {eps, omega_stop, omega_perf, spl, episodes}, runtime: {agent_fps, env_fps}}``),
``summary.md`` (the paper's table layout), ``run.json`` (run details, detailed timing),
``config_resolved.yaml`` and ``videos/`` (``video=N``), all written atomically once every episode is
done. Ctrl-C writes nothing and exits with status 130; configuration
errors print a message and exit with status 2.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

log = logging.getLogger("findview.eval")


@hydra.main(version_base="1.3", config_path="../configs", config_name="eval")
def main(cfg: DictConfig) -> None:
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    out_dir = Path(hc.runtime.output_dir)
    try:
        from findview_baselines.evaluation.evaluate import EvalError, evaluate
    except KeyboardInterrupt:
        print("eval: interrupted; nothing was written", file=sys.stderr)
        sys.exit(130)
    try:
        evaluate(cfg, out_dir, choices=dict(hc.runtime.choices), overrides=list(hc.overrides.task))
    except KeyboardInterrupt:
        print(f"eval: interrupted; no results were written to {out_dir}", file=sys.stderr)
        sys.exit(130)
    except EvalError as err:
        print(f"eval: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
