"""Evaluate an agent on the static episodes of a data set split (config ``configs/eval.yaml``).

Examples::

    python tools/eval.py agent=orb                                  # synthetic data set, test split
    python tools/eval.py agent=sift dataset=folder dataset.root=<dir> dataset.out_dir=<dir> split=test
    python tools/eval.py checkpoint=<run>/checkpoints/best.pth difficulty=hard   # view size, FoV, model from it
    python tools/eval.py agent=oracle episodes=<episode file> video=2
    python tools/eval.py -m agent=sift corruption.name=all corruption.severity=1,3
    python tools/eval.py -m agent=sift agent.d_thresh=10,20,30,40,50,60,70,80,90,100,inf split=val difficulty=easy

The run folder (``hydra.run.dir``; named after the agent, or after the checkpoint's run) receives
``episodes.jsonl`` (one record per episode), ``summary.json``, ``summary.md`` (the paper's table layout),
``run.json``, ``config_resolved.yaml``, ``videos/`` (``video=N``) and ``traces.jsonl`` (``trace=true``: per
episode and step the pose, the action and the learned agent's STOP probability), all written atomically once every
episode is done, and ``summary.md`` (the result table) is printed on stdout at the end. ``checkpoint=``
implies ``agent=ppo`` (so ``agent.revisit_penalty=0`` and the other learned-agent keys are valid with it).
Ctrl-C writes nothing and exits with status 130; problems with the input (data made from another root or
other settings, an unusable checkpoint, an output folder that cannot be written) print one line and exit
with status 2.
"""

from __future__ import annotations

from findview_baselines.cli import ToolContext, run_tool
from findview_baselines.config import EvalConfig


def main(cfg: EvalConfig, ctx: ToolContext) -> None:
    """Evaluate the validated config's agent into the run folder and print the result table."""
    from findview_baselines.evaluation.evaluate import evaluate

    evaluate(cfg, ctx.run_dir, choices=ctx.choices, overrides=ctx.overrides)
    table = ctx.run_dir / "summary.md"
    if table.is_file():
        print(table.read_text(), flush=True)


if __name__ == "__main__":
    from findview_baselines.evaluation.evaluate import checkpoint_implies_agent

    run_tool("eval", main, implied=checkpoint_implies_agent)
