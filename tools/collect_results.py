#!/usr/bin/env python
"""Gather a ``tools/eval.py`` multirun into the paper's tables.

Usage::

    python tools/eval.py -m agent=sift agent.d_thresh=10,20,30,40,50,60,70,80,90,100,inf split=val difficulty=easy
    python tools/collect_results.py multirun/eval/<...>/<date>          # the sweep folder
    python tools/collect_results.py <sweep folder> out=configs/agent/my_sift.yaml table=thresholds.md
    python tools/collect_results.py <sweep folder> layout=corruption    # Tables 8-11

Reads every run's ``.hydra/config.yaml``, ``run.json`` and ``summary.json``. Runs that differ in any
setting other than the table's rows and columns (FoV, view size, data set, split, episode file,
checkpoint, corruption, seed, ...) are never merged: each such setting gets its own table, titled with
the values that tell it apart. Two runs with identical settings in one cell are reported on stderr.

``layout=thresholds`` (default): the d_thresh search of the paper's Tables 13-15 (rows difficulty x
agent, columns the thresholds, cells the mean localization error eps, the best of each row in bold),
written to ``<sweep folder>/thresholds.md`` (or ``table=<path>``); then, per agent and data set, the best
``d_thresh`` of each difficulty (lowest eps among the runs in which some episode ended by ``stop``; ties:
higher SPL, then the smaller threshold) is written as the agent config
``<sweep folder>/<agent>_tuned_<dataset>.yaml`` (or ``out=<path>``); copy it into ``configs/agent/`` and
the benchmark uses it with ``agent=<agent>_tuned_<dataset>``. Runs of several settings (e.g.
``-m sim=fov90,fov60``) give one config per setting, named with a suffix
(``<agent>_tuned_<dataset>_fov60_height192.yaml``). Only validation-split runs may pick thresholds: with
test runs only, the tool stops with status 2 unless ``allow_test_tuning=true``.

A run in which no episode stopped (``omega_stop`` 0: every episode ran to ``T``) is marked ``(no stop)``
in the table and never picked: a difficulty where no run stopped is said on stderr and left out of the
config (it keeps the base config's threshold); an agent where no run stopped at all gets no config. An
existing config file with other contents is never replaced unless ``overwrite=true`` (status 2).

``layout=corruption``: the paper's Tables 8-11 (eps averaged over the three difficulties, one column per
corruption grouped by category with ``clear`` first, one row per agent, one table per severity), written
to ``<sweep folder>/corruptions.md`` (or ``table=<path>``); no config is written. Each run's corruption and
severity come from its ``run.json`` (keys ``corruption``, ``severity``) or its config; absent: clear.

Options are ``key=value`` (or ``--key value``): ``layout``, ``out``, ``table``, ``metric`` (``eps``; also
``spl``, ``omega_perf``, ``omega_stop``: the tuned config always minimises eps), ``write_config``
(``true``), ``allow_test_tuning`` (``false``), ``overwrite`` (``false``). Exit status 2 with one line on stderr for user errors.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import findview  # noqa: F401  (the CPU thread policy, before anything imports torch)
from findview.utils import write_text
from findview_baselines.evaluation.results import (
    CollectError,
    corruption_table,
    dataset_overrides,
    find_runs,
    format_threshold,
    threshold_table,
    tuned_config_text,
    tuned_thresholds,
)

METRICS = ("eps", "spl", "omega_perf", "omega_stop")
LAYOUTS = ("thresholds", "corruption")
TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


class UsageError(Exception):
    """A bad option value (one line, exit status 2)."""


def _bool(name: str, value: str) -> bool:
    v = str(value).strip().lower()
    if v in TRUE:
        return True
    if v in FALSE:
        return False
    raise UsageError(f"{name}={value!r}: expected true or false")


def parse_args(argv: list[str]) -> argparse.Namespace:
    """argparse, with ``key=value`` words turned into ``--key value``."""
    words: list[str] = []
    for w in argv:
        if "=" in w and not w.startswith("-"):
            k, v = w.split("=", 1)
            words += [f"--{k}", v]
        else:
            words.append(w)
    p = argparse.ArgumentParser(description="Collect a tools/eval.py multirun into the paper's tables.")
    p.add_argument("multirun_dir", help="the multirun (sweep) folder of tools/eval.py -m")
    p.add_argument("--layout", default="thresholds", choices=LAYOUTS, help="thresholds (Tables 13-15) or corruption (Tables 8-11)")
    p.add_argument("--out", default=None, help="tuned agent config path (default <multirun_dir>/<agent>_tuned_<dataset>.yaml)")
    p.add_argument("--table", default=None, help="markdown table path (default <multirun_dir>/thresholds.md or corruptions.md)")
    p.add_argument("--metric", default="eps", choices=METRICS, help="metric shown in the table (default eps)")
    p.add_argument("--write_config", "--write-config", default="true", help="write the tuned agent config (true/false)")
    p.add_argument("--allow_test_tuning", "--allow-test-tuning", nargs="?", const="true", default="false",
                   help="allow picking d_thresh from non-validation (test) runs (true/false)")
    p.add_argument("--overwrite", nargs="?", const="true", default="false",
                   help="replace an existing tuned config file with other contents (true/false)")
    return p.parse_args(words)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        return _run(args)
    except (UsageError, CollectError, FileNotFoundError, PermissionError) as err:
        print(f"collect_results: error: {err}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    write_config = _bool("write_config", args.write_config)
    allow_test = _bool("allow_test_tuning", args.allow_test_tuning)
    overwrite = _bool("overwrite", args.overwrite)
    root = Path(args.multirun_dir)
    warn = lambda m: print(f"warning: {m}", file=sys.stderr)  # noqa: E731
    runs = find_runs(root, warn=warn)
    if not runs:
        raise FileNotFoundError(f"no finished tools/eval.py runs (.hydra/config.yaml + summary.json) under {root}")
    if args.layout == "corruption":
        table = corruption_table(runs, args.metric, warn=warn)
        table_path = Path(args.table) if args.table else root / "corruptions.md"
        header = f"# Corruptions: {root}\n\n{len(runs)} runs. {args.metric}, mean over the difficulties; * = some difficulty missing.\n\n"
    else:
        table = threshold_table(runs, args.metric, warn=warn)
        table_path = Path(args.table) if args.table else root / "thresholds.md"
        header = f"# d_thresh search: {root}\n\n{len(runs)} runs.\n\n"
    write_text(table_path, header + table)
    print(table)
    print(f"table: {table_path}")
    if args.layout != "thresholds" or not write_config:
        return 0

    best = tuned_thresholds(runs, allow_test_tuning=allow_test, warn=warn)
    for (label, dataset, _), (_, group) in best.items():
        agents = {r.agent for r in group.runs if r.dataset == dataset}
        if label not in agents:
            raise CollectError(
                f"runs of {label.split(' (')[0]} differ in agent settings ({label}): a tuned config extends one "
                "agent config; collect each setting's folder separately, or pass write_config=false"
            )
    if not best:
        print("no tuned config written: no agent stopped in any episode of any run (see the warnings)")
        return 0
    if args.out and len(best) > 1:
        names = ", ".join(f"{a}/{d}" + (f"/{s}" if s else "") for a, d, s in best)
        raise CollectError(f"out= names one file but the runs hold several agents / data sets / settings ({names})")
    files: list[tuple[Path, str, str]] = []
    for (agent, dataset, suffix), (thresholds, group) in best.items():
        name = f"{agent}_tuned_{dataset}" + (f"_{suffix}" if suffix else "")
        path = Path(args.out) if args.out else root / f"{name}.yaml"
        settings = ", ".join(f"{k}={v}" for k, v in group.context if k not in ("split", "dataset.name"))
        evaluated = {d for r in group.runs if r.agent == agent for d in r.difficulties()}
        text = tuned_config_text(agent, dataset, thresholds, source=str(root), split=group.split,
                                 name=path.stem, settings=settings, untuned=sorted(evaluated - set(thresholds)),
                                 dataset_args=dataset_overrides(group.runs[0].path))
        picks = ", ".join(f"{d}={format_threshold(t)}" for d, t in thresholds.items())
        tag = "" if all(r.is_val for r in group.runs) else " (from test-split runs: allow_test_tuning=true)"
        where = f" ({settings})" if settings else ""
        files.append((path, text, f"best d_thresh for {agent} on {dataset}{where}: {picks} -> {path}{tag}"))
    for path, text, _ in files:  # refuse before writing anything
        if path.is_file() and not overwrite and path.read_text() != text:
            raise CollectError(f"{path} exists with other contents; move it away or pass overwrite=true")
    for path, text, line in files:
        unchanged = path.is_file() and path.read_text() == text
        write_text(path, text)
        print(line + (" (unchanged)" if unchanged else ""))
    if not args.out:
        print(f"to use a tuned config, copy it into configs/agent/: cp {files[0][0]} configs/agent/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
