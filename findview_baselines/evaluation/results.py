"""The result files of one evaluation run (``episodes.jsonl``, ``run.json``, ``config_resolved.yaml``,
``summary.md``, ``summary.json``; with ``trace=true`` ``traces.jsonl``): :func:`make_summary`,
:func:`summary_markdown`, :func:`write_results`, :func:`write_traces`.

The tables built from a multirun of such runs live in ``collect.py``, the agent title and the
non-default settings of a run in ``run_info.py``; their names are re-exported here.

``summary.json`` schema (fractions in ``[0, 1]``, ``eps`` in degrees)::

    {"<difficulty>": {"eps": float, "omega_stop": float, "omega_perf": float, "spl": float,
                      "episodes": int}, ...,
     "runtime": {"agent_fps": float, "env_fps": float}}
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from findview.metrics import RECORD_KEYS, format_table, summarize
from findview.utils import atomic_write, write_json, write_text
from findview_baselines.evaluation.collect import (
    CLEAR,
    CORRUPTION_CATEGORIES,
    IGNORED_KEYS,
    LEARNED_AGENT_KEYS,
    CollectError,
    EvalRun,
    RunGroup,
    agent_labels,
    best_thresholds,
    config_suffix,
    corruption_columns,
    corruption_of,
    corruption_table,
    find_runs,
    format_threshold,
    group_runs,
    mean_over_difficulties,
    threshold_table,
    threshold_value,
    tuned_config_text,
    dataset_overrides,
    tuned_thresholds,
)
from findview_baselines.evaluation.run_info import (
    agent_title,
    learned_agent_info,
    non_default_settings,
    run_settings,
)

__all__ = [
    "EPISODE_FIELDS",
    "make_summary",
    "summary_markdown",
    "write_results",
    "write_traces",
    # re-exported from run_info.py and collect.py (the old import paths keep working)
    "agent_title",
    "learned_agent_info",
    "non_default_settings",
    "run_settings",
    "CORRUPTION_CATEGORIES",
    "CollectError",
    "EvalRun",
    "RunGroup",
    "find_runs",
    "group_runs",
    "agent_labels",
    "corruption_of",
    "tuned_thresholds",
    "config_suffix",
    "corruption_columns",
    "mean_over_difficulties",
    "corruption_table",
    "threshold_value",
    "format_threshold",
    "threshold_table",
    "best_thresholds",
    "tuned_config_text",
    "dataset_overrides",
    "CLEAR",
    "IGNORED_KEYS",
    "LEARNED_AGENT_KEYS",
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
    """``summary.md``: a title (a learned agent by its trainer and variant, see :func:`agent_title`), the
    run's settings that differ from the defaults (``meta["settings"]``, see :func:`non_default_settings`),
    the paper's table layout (one row: eps / omega_stop / omega_perf / SPL per difficulty), the
    per-difficulty episode counts and the runtime block (paper Table 12)."""
    groups = {k: v for k, v in summary.items() if k != "runtime"}
    meta = dict(meta or {})
    settings = meta.pop("settings", None)
    agent = agent_title(agent, meta)
    lines = [f"# {agent}" + (f" on {meta['dataset']} / {meta['split']}" if "dataset" in meta and "split" in meta else "")]
    if settings is not None:
        lines += ["", "Settings that differ from the defaults: " + (", ".join(f"`{x}`" for x in settings) if settings else "none")]
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


#: the keys of one ``traces.jsonl`` line, in order
TRACE_FIELDS = ("episode_id", "pitch", "yaw", "action", "stop_prob")


def write_traces(path: str | os.PathLike, records: Sequence[Mapping[str, Any]],
                 traces: Mapping[str, Mapping[str, Any]]) -> Path:
    """Write ``traces.jsonl`` atomically: one line per record, in the records' order (that of ``episodes.jsonl``),
    ``{"episode_id", "pitch", "yaw", "action", "stop_prob"}`` (:data:`TRACE_FIELDS`) from that episode's trace of
    :class:`~findview_baselines.evaluation.harness.TraceRecorder`: per step the pose before the action (integer
    degrees), the action (UP=0, DOWN=1, LEFT=2, RIGHT=3, STOP=4) and the agent's STOP probability (``null`` as a
    whole for an agent without one, ``null`` at a step without a value).

    Raises:
        ValueError: a record without a trace, or whose trace does not have ``steps`` actions.
    """
    rows = []
    for r in records:
        eid = r["episode_id"]
        if eid not in traces:
            raise ValueError(f"episode {eid}: no trace was recorded")
        trace = traces[eid]
        if len(trace["action"]) != r["steps"]:
            raise ValueError(f"episode {eid}: its trace has {len(trace['action'])} actions for {r['steps']} steps")
        rows.append({k: trace[k] for k in TRACE_FIELDS})

    def _write(tmp: str) -> None:
        with open(tmp, "w") as f:
            for row in rows:
                f.write(json.dumps(row) + "\n")

    return atomic_write(path, _write)


def write_results(
    out_dir: str | os.PathLike,
    records: Sequence[Mapping[str, Any]],
    runtime: Mapping[str, Any],
    agent: str,
    meta: Mapping[str, Any] | None = None,
    resolved_config: str | None = None,
    traces: Mapping[str, Mapping[str, Any]] | None = None,
) -> dict[str, Any]:
    """Write ``episodes.jsonl``, ``traces.jsonl`` (when ``traces`` is given, see :func:`write_traces`),
    ``run.json`` (meta + detailed runtime), ``config_resolved.yaml`` (when ``resolved_config`` is given),
    ``summary.md`` and, last, ``summary.json`` into ``out_dir``, each atomically. A learned agent's trainer and
    variant (from its checkpoint) and the settings that differ from the defaults (read from the run folder's
    ``.hydra/hydra.yaml``) join ``meta``. Returns the summary."""
    out = Path(out_dir)
    summary = make_summary(records, runtime)
    meta = dict(meta or {})
    if agent == "ppo" and meta.get("checkpoint"):
        meta.update(learned_agent_info(meta["checkpoint"]))
    if resolved_config is not None and "settings" not in meta:
        settings = run_settings(out, resolved_config)
        if settings is not None:
            meta["settings"] = settings
    _write_jsonl(out / "episodes.jsonl", records)
    if traces is not None:
        write_traces(out / "traces.jsonl", records, traces)
    write_json(out / "run.json", {"agent": agent, **dict(meta or {}), "runtime": dict(runtime)})
    if resolved_config is not None:
        write_text(out / "config_resolved.yaml", resolved_config)
    write_text(out / "summary.md", summary_markdown(summary, agent, meta))
    write_json(out / "summary.json", summary)
    return summary

