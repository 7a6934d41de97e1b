"""Evaluation outputs (``episodes.jsonl``, ``summary.json``, ``summary.md``) and the threshold search
tables built from a Hydra multirun of ``tools/eval.py`` (the paper's Tables 13-15).

``summary.json`` schema (fractions in ``[0, 1]``, ``eps`` in degrees)::

    {"<difficulty>": {"eps": float, "omega_stop": float, "omega_perf": float, "spl": float,
                      "episodes": int}, ...,
     "runtime": {"agent_fps": float, "env_fps": float}}
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from findview.episode import DIFFICULTIES
from findview.metrics import RECORD_KEYS, format_table, summarize
from findview.utils import atomic_write, write_json, write_text

__all__ = [
    "EPISODE_FIELDS",
    "make_summary",
    "summary_markdown",
    "write_results",
    "EvalRun",
    "find_runs",
    "threshold_value",
    "format_threshold",
    "threshold_table",
    "best_thresholds",
    "tuned_config_text",
]

#: the keys of one ``episodes.jsonl`` line, in order (the environment's episode record)
EPISODE_FIELDS = RECORD_KEYS


# --------------------------------------------------------------------------------------------------
# one evaluation run
# --------------------------------------------------------------------------------------------------
def make_summary(records: Iterable[Mapping[str, Any]], runtime: Mapping[str, float]) -> dict[str, Any]:
    """``summary.json`` content: :func:`findview.metrics.summarize` per difficulty plus ``runtime``."""
    out: dict[str, Any] = {}
    for group, m in summarize(records).items():
        out[group] = {
            "eps": float(m["eps"]),
            "omega_stop": float(m["omega_stop"]),
            "omega_perf": float(m["omega_perf"]),
            "spl": float(m["spl"]),
            "episodes": int(m["episodes"]),
        }
    out["runtime"] = {"agent_fps": float(runtime["agent_fps"]), "env_fps": float(runtime["env_fps"])}
    return out


def summary_markdown(summary: Mapping[str, Any], agent: str, meta: Mapping[str, Any] | None = None) -> str:
    """``summary.md``: the paper's table layout (one row: eps / omega_stop / omega_perf / SPL per
    difficulty), the per-difficulty episode counts and the runtime block (paper Table 12)."""
    groups = {k: v for k, v in summary.items() if k != "runtime"}
    meta = dict(meta or {})
    lines = [f"# {agent}" + (f" on {meta['dataset']} / {meta['split']}" if "dataset" in meta and "split" in meta else "")]
    details = ", ".join(f"{k}: {v}" for k, v in meta.items() if k not in ("dataset", "split") and v is not None)
    if details:
        lines += ["", details]
    lines += ["", "eps: mean localization error (degrees, lower is better); stop, perf, SPL in percent.", ""]
    lines.append(format_table({agent: groups}) if groups else "(no episodes)")
    lines += ["", "| difficulty | episodes |", "|---|---|"]
    lines += [f"| {g} | {int(m['episodes'])} |" for g, m in groups.items()]
    rt = summary.get("runtime", {})
    lines += [
        "",
        "## Runtime",
        "",
        "| agent FPS (agent only) | env FPS (per-env steps) |",
        "|---|---|",
        f"| {rt.get('agent_fps', 0.0):.1f} | {rt.get('env_fps', 0.0):.1f} |",
    ]
    return "\n".join(lines) + "\n"


def _write_jsonl(path: Path, records: Sequence[Mapping[str, Any]]) -> Path:
    def _write(tmp: str) -> None:
        with open(tmp, "w") as f:
            for r in records:
                row = {k: r[k] for k in EPISODE_FIELDS if k in r}
                row.update({k: v for k, v in r.items() if k not in row})
                f.write(json.dumps(row) + "\n")

    return atomic_write(path, _write)


def write_results(
    out_dir: str | os.PathLike,
    records: Sequence[Mapping[str, Any]],
    runtime: Mapping[str, Any],
    agent: str,
    meta: Mapping[str, Any] | None = None,
    resolved_config: str | None = None,
) -> dict[str, Any]:
    """Write ``episodes.jsonl``, ``run.json`` (meta + detailed runtime), ``config_resolved.yaml`` (when
    ``resolved_config`` is given), ``summary.md`` and, last, ``summary.json`` into ``out_dir``, each
    atomically. Returns the summary."""
    out = Path(out_dir)
    summary = make_summary(records, runtime)
    _write_jsonl(out / "episodes.jsonl", records)
    write_json(out / "run.json", {"agent": agent, **dict(meta or {}), "runtime": dict(runtime)})
    if resolved_config is not None:
        write_text(out / "config_resolved.yaml", resolved_config)
    write_text(out / "summary.md", summary_markdown(summary, agent, meta))
    write_json(out / "summary.json", summary)
    return summary


# --------------------------------------------------------------------------------------------------
# threshold search (collect a multirun)
# --------------------------------------------------------------------------------------------------
@dataclass
class EvalRun:
    """One finished ``tools/eval.py`` run of a multirun folder."""

    path: Path
    agent: str
    dataset: str
    split: str
    difficulty: str | None
    d_thresh: Any
    summary: dict[str, Any]
    config: dict[str, Any] = field(repr=False, default_factory=dict)

    def difficulties(self) -> list[str]:
        """The difficulties this run evaluated (present in its summary)."""
        return [d for d in self.summary if d != "runtime" and (self.difficulty is None or d == self.difficulty)]


def threshold_value(d_thresh: Any, difficulty: str) -> float:
    """The ``d_thresh`` used for ``difficulty``: a scalar (``inf``/``None``/``"inf"`` = no threshold)
    or a mapping per difficulty (missing -> its ``default`` entry, else ``inf``)."""
    if isinstance(d_thresh, Mapping):
        v = d_thresh.get(difficulty, d_thresh.get("default", math.inf))
        return threshold_value(v, difficulty)
    if d_thresh is None:
        return math.inf
    if isinstance(d_thresh, str):
        s = d_thresh.strip().lower()
        return math.inf if s in ("inf", "+inf", "infinity", ".inf", "none", "null", "") else float(s)
    return float(d_thresh)


def format_threshold(x: float) -> str:
    """``10``, ``12.5``, ``inf``."""
    if math.isinf(x):
        return "inf"
    return str(int(x)) if float(x).is_integer() else f"{x:g}"


def _load_config(run_dir: Path) -> dict[str, Any] | None:
    cfg_file = run_dir / ".hydra" / "config.yaml"
    if not cfg_file.is_file():
        return None
    from omegaconf import OmegaConf

    return OmegaConf.to_container(OmegaConf.load(cfg_file), resolve=False)  # type: ignore[return-value]


def find_runs(root: str | os.PathLike, warn: Any = None) -> list[EvalRun]:
    """Every finished eval run under ``root`` (a multirun folder; runs are found at any depth by their
    ``.hydra/config.yaml``). Runs without ``summary.json`` (failed / interrupted) are skipped and passed
    to ``warn(message)`` when given."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"multirun folder not found: {root}")
    runs: list[EvalRun] = []
    for cfg_file in sorted(root.rglob(".hydra/config.yaml")):
        run_dir = cfg_file.parent.parent
        cfg = _load_config(run_dir)
        if cfg is None or "agent" not in cfg:
            continue
        summary_file = run_dir / "summary.json"
        if not summary_file.is_file():
            if warn is not None:
                warn(f"{run_dir}: no summary.json (failed or interrupted run), skipped")
            continue
        with open(summary_file) as f:
            summary = json.load(f)
        agent_cfg = cfg.get("agent") or {}
        dataset_cfg = cfg.get("dataset") or {}
        runs.append(
            EvalRun(
                path=run_dir,
                agent=str(agent_cfg.get("name", "?")),
                dataset=str(dataset_cfg.get("name", "?")) if isinstance(dataset_cfg, Mapping) else str(dataset_cfg),
                split=str(cfg.get("split", "?")),
                difficulty=cfg.get("difficulty"),
                d_thresh=agent_cfg.get("d_thresh"),
                summary=summary,
                config=cfg,
            )
        )
    return runs


def _collect(runs: Sequence[EvalRun], metric: str) -> dict[tuple[str, str, str], dict[str, dict[float, float]]]:
    """``{(dataset, split, agent): {difficulty: {threshold: metric value}}}`` (later runs win on duplicates)."""
    table: dict[tuple[str, str, str], dict[str, dict[float, float]]] = {}
    for run in runs:
        key = (run.dataset, run.split, run.agent)
        for d in run.difficulties():
            value = run.summary[d].get(metric)
            if value is None:
                continue
            table.setdefault(key, {}).setdefault(d, {})[threshold_value(run.d_thresh, d)] = float(value)
    return table


def _order_difficulties(names: Iterable[str]) -> list[str]:
    names = set(names)
    return [d for d in DIFFICULTIES if d in names] + sorted(names - set(DIFFICULTIES))


def _fmt_value(x: float, metric: str) -> str:
    if math.isnan(x):
        return "-"
    if metric == "eps" or metric == "episodes":
        return f"{x:.2f}" if metric == "eps" else str(int(x))
    return f"{100 * x:.1f}%"


def threshold_table(runs: Sequence[EvalRun], metric: str = "eps") -> str:
    """Markdown tables in the layout of the paper's Tables 13-15: one table per (dataset, split), rows
    difficulty x agent, columns the ``d_thresh`` values, cells ``metric`` (default ``eps``); the best
    value of each row is bold (lowest for ``eps``, highest otherwise; ties all bold)."""
    data = _collect(runs, metric)
    if not data:
        return "(no finished runs with a summary)\n"
    lower_is_better = metric == "eps"
    out: list[str] = []
    for ds_split in sorted({(k[0], k[1]) for k in data}):
        keys = [k for k in data if (k[0], k[1]) == ds_split]
        thresholds = sorted({t for k in keys for d in data[k].values() for t in d})
        diffs = _order_difficulties(d for k in keys for d in data[k])
        out.append(f"## {ds_split[0]} / {ds_split[1]}: {metric} per d_thresh (best in bold)")
        out.append("")
        out.append("| difficulty | agent | " + " | ".join(format_threshold(t) for t in thresholds) + " |")
        out.append("|---|---|" + "---|" * len(thresholds))
        for d in diffs:
            for k in sorted(keys, key=lambda k: k[2]):
                row = data[k].get(d)
                if not row:
                    continue
                vals = [v for v in row.values() if not math.isnan(v)]
                best = (min(vals) if lower_is_better else max(vals)) if vals else None
                cells = []
                for t in thresholds:
                    if t not in row:
                        cells.append("-")
                        continue
                    s = _fmt_value(row[t], metric)
                    cells.append(f"**{s}**" if best is not None and row[t] == best else s)
                out.append(f"| {d} | {k[2]} | " + " | ".join(cells) + " |")
        out.append("")
    return "\n".join(out)


def best_thresholds(runs: Sequence[EvalRun]) -> dict[tuple[str, str], dict[str, float]]:
    """``{(agent, dataset): {difficulty: best d_thresh}}``: the lowest mean ``eps``; ties go to the
    higher SPL, then to the smaller threshold (the paper notes tied thresholds give identical runs).

    When the runs hold several splits of one data set, the ``val`` runs decide (the paper tunes on val).
    """
    eps = _collect(runs, "eps")
    spl = _collect(runs, "spl")
    best: dict[tuple[str, str], dict[str, float]] = {}
    # val last, so that its picks overwrite any other split's
    for (dataset, split, agent), per_diff in sorted(eps.items(), key=lambda kv: (kv[0][1] == "val", kv[0])):
        for d, row in per_diff.items():
            candidates = [t for t, v in row.items() if not math.isnan(v)]
            if not candidates:
                continue
            s = spl.get((dataset, split, agent), {}).get(d, {})
            t_best = min(candidates, key=lambda t: (row[t], -s.get(t, 0.0), t))
            best.setdefault((agent, dataset), {})[d] = t_best
    return best


def _yaml_number(x: float) -> str:
    if math.isinf(x):
        return ".inf"
    return str(int(x)) if float(x).is_integer() else repr(float(x))


def tuned_config_text(
    agent: str, dataset: str, thresholds: Mapping[str, float], source: str = "", split: str = "val"
) -> str:
    """An ``agent`` group config that extends ``<agent>.yaml`` with the tuned ``d_thresh`` per difficulty.

    Difficulties without a tuned value keep the base config's threshold.
    """
    lines = [
        f"# {agent} with d_thresh tuned on the {dataset} {split} episodes (lowest mean eps per difficulty),",
        "# written by tools/collect_results.py" + (f" from {source}" if source else "") + ".",
        f"# Use it with: python tools/eval.py agent={agent}_tuned_{dataset} dataset={dataset}",
        "defaults:",
        f"  - {agent}",
        "  - _self_",
        "d_thresh:",
    ]
    for d in _order_difficulties(thresholds):
        lines.append(f"  {d}: {_yaml_number(thresholds[d])}")
    return "\n".join(lines) + "\n"
