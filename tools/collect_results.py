#!/usr/bin/env python
"""Gather a ``tools/eval.py`` multirun (the d_thresh search) into the paper's validation tables.

Usage::

    python tools/eval.py -m agent=sift agent.d_thresh=10,20,30,40,50,60,70,80,90,100,inf split=val difficulty=easy
    python tools/collect_results.py multirun/eval/<...>/<date>          # the sweep folder
    python tools/collect_results.py <sweep folder> out=configs/agent/my_sift.yaml table=thresholds.md

Reads every run's ``.hydra/config.yaml`` (agent.name, agent.d_thresh, difficulty, dataset.name, split)
and ``summary.json``, then

- prints and writes the table of the paper's Tables 13-15 (rows difficulty x agent, columns the
  thresholds, cells the mean localization error eps, the best of each row in bold) to
  ``<sweep folder>/thresholds.md`` (or ``table=<path>``);
- writes, per agent and data set, the best ``d_thresh`` of each difficulty (lowest eps; ties: higher
  SPL, then the smaller threshold) as the agent config ``configs/agent/<agent>_tuned_<dataset>.yaml``
  (or ``out=<path>``), which the benchmark uses with ``agent=<agent>_tuned_<dataset>``.

Options are ``key=value`` (or ``--key value``): ``out``, ``table``, ``metric`` (``eps``; also ``spl``,
``omega_perf``, ``omega_stop`` for extra tables: the tuned config always minimises eps), ``write_config``
(``true``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from findview.utils import write_text  # noqa: E402
from findview_baselines.evaluation.results import (  # noqa: E402
    best_thresholds,
    find_runs,
    format_threshold,
    threshold_table,
    tuned_config_text,
)

METRICS = ("eps", "spl", "omega_perf", "omega_stop")


def parse_args(argv: list[str]) -> argparse.Namespace:
    """argparse, with ``key=value`` words turned into ``--key value``."""
    words: list[str] = []
    for w in argv:
        if "=" in w and not w.startswith("-"):
            k, v = w.split("=", 1)
            words += [f"--{k}", v]
        else:
            words.append(w)
    p = argparse.ArgumentParser(description="Collect a tools/eval.py multirun into the d_thresh validation table.")
    p.add_argument("multirun_dir", help="the multirun (sweep) folder of tools/eval.py -m")
    p.add_argument("--out", default=None, help="tuned agent config path (default configs/agent/<agent>_tuned_<dataset>.yaml)")
    p.add_argument("--table", default=None, help="markdown table path (default <multirun_dir>/thresholds.md)")
    p.add_argument("--metric", default="eps", choices=METRICS, help="metric shown in the table (default eps)")
    p.add_argument("--write_config", default="true", help="write the tuned agent config (true/false)")
    return p.parse_args(words)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    root = Path(args.multirun_dir)
    try:
        runs = find_runs(root, warn=lambda m: print(f"warning: {m}", file=sys.stderr))
    except FileNotFoundError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(f"error: no finished tools/eval.py runs (.hydra/config.yaml + summary.json) under {root}", file=sys.stderr)
        return 2
    table = threshold_table(runs, args.metric)
    table_path = Path(args.table) if args.table else root / "thresholds.md"
    header = f"# d_thresh search: {root}\n\n{len(runs)} runs.\n\n"
    write_text(table_path, header + table)
    print(table)
    print(f"table: {table_path}")

    if str(args.write_config).lower() not in ("1", "true", "yes"):
        return 0
    best = best_thresholds(runs)
    if args.out and len(best) > 1:
        names = ", ".join(f"{a}/{d}" for a, d in best)
        print(f"error: out= names one file but the runs hold several agents / data sets ({names})", file=sys.stderr)
        return 2
    for (agent, dataset), thresholds in best.items():
        path = Path(args.out) if args.out else REPO / "configs" / "agent" / f"{agent}_tuned_{dataset}.yaml"
        splits = sorted({r.split for r in runs if r.agent == agent and r.dataset == dataset})
        split = "val" if "val" in splits else ",".join(splits)
        write_text(path, tuned_config_text(agent, dataset, thresholds, source=str(root), split=split))
        picks = ", ".join(f"{d}={format_threshold(t)}" for d, t in thresholds.items())
        print(f"best d_thresh for {agent} on {dataset}: {picks} -> {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
