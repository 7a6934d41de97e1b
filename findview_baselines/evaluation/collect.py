"""The tables built from a Hydra multirun of ``tools/eval.py`` (used by ``tools/collect_results.py`` and
the robustness benchmark): finding the finished runs (:func:`find_runs`), grouping them into tables
(:func:`group_runs`), the threshold search (the paper's Tables 13-15), the tuned ``d_thresh`` configs
(:func:`tuned_thresholds`, :func:`tuned_config_text`) and the corruption tables (Tables 8-11).

Collecting never merges runs that differ in a setting other than the table's rows and columns: such
runs go to separate tables (:func:`group_runs`). A tuned config is only written from validation runs
unless asked (:func:`tuned_thresholds`).
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from findview.corruptions import CATEGORIES
from findview.episode import DIFFICULTIES
from findview_baselines.evaluation.run_info import _flatten, agent_title, learned_agent_info

__all__ = [
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


#: corruption categories and names, in the column order of the paper's corruption tables
CORRUPTION_CATEGORIES: dict[str, tuple[str, ...]] = dict(CATEGORIES)
#: the name of "no corruption" (the ``clear`` column)
CLEAR = "none"

#: config keys that never change the numbers (threads, progress bars, videos, traces, the batch of parallel
#: episodes) and Hydra's own: ignored when telling runs apart
IGNORED_KEYS = (
    "hydra", "progress", "video", "video_fps", "video_pano_height", "trace", "num_envs", "torch_threads",
    "sim.device", "sim.prefetch_workers", "sim.bank_mb", "agent.threads", "agent.torch_threads",
)


class CollectError(ValueError):
    """A multirun that cannot be collected as asked (one line for the user)."""


@dataclass
class EvalRun:
    """One finished ``tools/eval.py`` run of a multirun folder.

    ``settings`` are the run's config (``.hydra/config.yaml``) flattened to dotted keys, plus the
    ``corruption`` and ``severity`` of its targets, as comparable strings: runs whose settings differ
    (other than in the columns / rows of a table) are never merged into one table. Null settings are
    left out (null and absent are the same setting).
    """

    path: Path
    agent: str
    dataset: str
    split: str
    difficulty: str | None
    d_thresh: Any
    summary: dict[str, Any]
    config: dict[str, Any] = field(repr=False, default_factory=dict)
    meta: dict[str, Any] = field(repr=False, default_factory=dict)
    corruption: str = CLEAR
    severity: int = 0
    settings: dict[str, str] = field(repr=False, default_factory=dict)

    @property
    def learned(self) -> bool:
        """A learned agent (its ``checkpoint``): titled by trainer and variant, never tuned."""
        return self.agent == "ppo" and bool(self.config.get("checkpoint"))

    @property
    def title(self) -> str:
        """The agent's name in tables (:func:`agent_title`): ``orb``, ``dagger direct``, ..."""
        if not self.learned:
            return self.agent
        info = {k: self.meta[k] for k in ("trainer", "variant") if self.meta.get(k)}
        if "trainer" not in info:  # runs of an older eval: ask the checkpoint
            info = {**learned_agent_info(self.config["checkpoint"]), **info}
        agent_cfg = self.config.get("agent") if isinstance(self.config.get("agent"), Mapping) else {}
        if "variant" not in info and agent_cfg.get("variant"):
            info["variant"] = agent_cfg["variant"]
        return agent_title(self.agent, {"checkpoint": self.config["checkpoint"], **info})

    def stopped(self, difficulty: str) -> bool:
        """Whether any episode of ``difficulty`` ended by ``stop`` (``omega_stop > 0``; unknown: yes)."""
        value = self.summary[difficulty].get("omega_stop")
        return value is None or float(value) > 0

    def difficulties(self) -> list[str]:
        """The difficulties this run evaluated (present in its summary)."""
        return [
            d for d in self.summary
            if d not in ("runtime", "meta") and isinstance(self.summary[d], Mapping)
            and (self.difficulty is None or d == self.difficulty)
        ]

    @property
    def is_val(self) -> bool:
        """Whether the run evaluated a validation split (the only one a tuned config may come from)."""
        return self.split == "val" or self.split.startswith("val_")


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
    """A run's config: the resolved one ``tools/eval.py`` writes (``config_resolved.yaml``: values, so runs made
    from YAML files that spell the same value differently, ``${sim.fov}`` or ``90``, compare equal), else Hydra's
    ``.hydra/config.yaml`` as composed (unresolved: its run-name resolvers exist only inside the tool)."""
    from omegaconf import OmegaConf

    resolved = run_dir / "config_resolved.yaml"
    if resolved.is_file():
        return OmegaConf.to_container(OmegaConf.load(resolved), resolve=False)  # type: ignore[return-value]
    cfg_file = run_dir / ".hydra" / "config.yaml"
    if not cfg_file.is_file():
        return None
    return OmegaConf.to_container(OmegaConf.load(cfg_file), resolve=False)  # type: ignore[return-value]


def _read_json_dict(path: Path) -> dict[str, Any]:
    if not path.is_file():
        return {}
    try:
        with open(path) as f:
            obj = json.load(f)
    except (OSError, json.JSONDecodeError):
        return {}
    return obj if isinstance(obj, dict) else {}



def _ignored(key: str) -> bool:
    return any(key == k or key.startswith(k + ".") for k in IGNORED_KEYS)


def corruption_of(cfg: Mapping[str, Any], meta: Mapping[str, Any]) -> tuple[str, int]:
    """``(name, severity)`` of a run's target corruption: from its run meta (``run.json`` /
    ``summary.json["meta"]`` keys ``corruption``, ``severity``), else from its config (``corruption:
    <name>`` or ``corruption: {name, severity}``, ``severity``); ``("none", 0)`` when absent."""
    name: Any = meta.get("corruption")
    severity: Any = meta.get("severity")
    c = cfg.get("corruption")
    if isinstance(c, Mapping):
        name = c.get("name") if name is None else name
        severity = c.get("severity") if severity is None else severity
    elif name is None:
        name = c
    if severity is None:
        severity = cfg.get("severity")
    name = CLEAR if name in (None, "", "none", "None", "clear", "null") else str(name)
    try:
        sev = int(severity) if severity not in (None, "", "null") else 0
    except (TypeError, ValueError):
        sev = 0
    return name, (0 if name == CLEAR else sev)


def find_runs(root: str | os.PathLike, warn: Any = None) -> list[EvalRun]:
    """Every finished eval run under ``root`` (a multirun folder; runs are found at any depth by their
    ``.hydra/config.yaml``). Runs without ``summary.json`` (failed / interrupted) are skipped and passed
    to ``warn(message)`` when given. The run meta is read from ``run.json`` (written by ``tools/eval.py``)
    and ``summary.json["meta"]`` when present."""
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
        summary = _read_json_dict(summary_file)
        meta = {**_read_json_dict(run_dir / "run.json"), **(summary.get("meta") or {})}
        agent_cfg = cfg.get("agent") or {}
        dataset_cfg = cfg.get("dataset") or {}
        corruption, severity = corruption_of(cfg, meta)
        # A null setting is the same as an absent one: a run made before an optional field existed
        # (``corruption.weights``) belongs in the same table as a run with the field left null
        settings = {k: v for k, v in _flatten(cfg).items() if not _ignored(k) and v != "null"}
        settings = {k: v for k, v in settings.items() if k not in ("corruption", "corruption.name", "corruption.severity", "severity")}
        settings["corruption"], settings["severity"] = corruption, str(severity)
        split = str(cfg.get("split", "?"))
        if cfg.get("episodes"):  # an explicit episode file: the config's split is not what ran
            split = str(meta.get("split") or Path(str(cfg["episodes"])).stem)
        runs.append(
            EvalRun(
                path=run_dir,
                agent=str(agent_cfg.get("name", "?")),
                dataset=str(dataset_cfg.get("name", "?")) if isinstance(dataset_cfg, Mapping) else str(dataset_cfg),
                split=split,
                difficulty=cfg.get("difficulty"),
                d_thresh=agent_cfg.get("d_thresh"),
                summary=summary,
                config=cfg,
                meta=meta,
                corruption=corruption,
                severity=severity,
                settings=settings,
            )
        )
    return runs


# ---------------------------------------------------------------------------------------- grouping
@dataclass
class RunGroup:
    """Runs that belong in one table: equal in every setting but the table's rows and columns.

    ``context`` holds the settings that differ between the groups of one collection (``sim.fov``,
    ``split``, ``corruption``, ...), ``(key, value)`` pairs in key order; empty for a single group.
    """

    context: tuple[tuple[str, str], ...]
    runs: list[EvalRun]

    @property
    def dataset(self) -> str:
        return self.runs[0].dataset

    @property
    def split(self) -> str:
        return self.runs[0].split

    @property
    def max_steps(self) -> str:
        """``T`` (``task.max_steps``) of the group's runs (``?`` when their configs do not say)."""
        values = sorted({r.settings.get("task.max_steps", "?") for r in self.runs})
        return ", ".join(values)

    def title(self) -> str:
        """``<dataset> / <split>`` plus the distinguishing settings and the episode limit ``T``."""
        extra = ", ".join(f"{k}={v}" for k, v in self.context if k not in ("dataset.name", "split", "task.max_steps"))
        return f"{self.dataset} / {self.split}" + (f" ({extra})" if extra else "") + f", T = {self.max_steps}"


def _row_keys(mode: str) -> Callable[[str], bool]:
    """Whether a settings key is a row / column of the table (not a table-defining setting)."""
    if mode == "thresholds":  # rows: difficulty x agent; columns: d_thresh
        return lambda k: k == "difficulty" or k == "agent" or k.startswith("agent.")
    if mode != "corruption":
        raise ValueError(f"unknown table layout {mode!r}; expected thresholds or corruption")
    # corruption: rows agent, columns corruption, one table per severity, eps averaged over difficulties.
    # A learned agent is its checkpoint, and its view size comes from it: rows too, not separate tables
    return lambda k: k in ("difficulty", "corruption", "severity", "agent", *LEARNED_AGENT_KEYS) or k.startswith("agent.")


LEARNED_AGENT_KEYS = ("checkpoint", "sim.height", "sim.width")


def group_runs(runs: Sequence[EvalRun], mode: str = "thresholds") -> list[RunGroup]:
    """Split ``runs`` into tables: runs differing in any setting that is not a row or column of the
    ``mode``'s layout (``thresholds`` or ``corruption``) go to different groups."""
    is_row = _row_keys(mode)
    keys = sorted({k for r in runs for k in r.settings if not is_row(k)})
    varying = [k for k in keys if len({r.settings.get(k, "<unset>") for r in runs}) > 1]
    groups: dict[tuple[tuple[str, str], ...], list[EvalRun]] = {}
    for r in runs:
        ctx = tuple((k, r.settings.get(k, "<unset>")) for k in varying)
        groups.setdefault(ctx, []).append(r)
    return [RunGroup(ctx, rs) for ctx, rs in sorted(groups.items())]


def _short_paths(paths: Sequence[str]) -> dict[str, str]:
    """The shortest trailing part of each path (whole components) that tells it apart from the others."""
    parts = {p: Path(p).parts for p in set(paths)}
    short: dict[str, str] = {}
    for p, comps in parts.items():
        for n in range(1, len(comps) + 1):
            tail = comps[-n:]
            if all(q == p or tuple(other[-n:]) != tuple(tail) for q, other in parts.items()):
                break
        short[p] = str(Path(*tail)) if comps else p
    return short


def agent_labels(runs: Sequence[EvalRun], swept: Sequence[str] = ("agent.d_thresh",)) -> dict[Path, str]:
    """Row label per run folder: the agent's name, plus the agent settings other than ``swept`` in
    which runs of that agent differ (``orb (agent.n_features=1000)``; a learned agent is titled by its
    trainer and variant, its checkpoint by the shortest distinct end of its path, ``dagger direct
    (checkpoint=before.pth)``), so that they are never merged."""
    labels: dict[Path, str] = {}
    by_name: dict[str, list[EvalRun]] = {}
    for r in runs:
        by_name.setdefault(r.title, []).append(r)
    for name, rs in by_name.items():
        keys = sorted({k for r in rs for k in r.settings
                       if (k == "agent" or k.startswith("agent.") or k in LEARNED_AGENT_KEYS) and k not in swept})
        varying = [k for k in keys if k != "agent.name" and len({r.settings.get(k, "<unset>") for r in rs}) > 1]
        short = _short_paths([r.settings.get("checkpoint", "<unset>") for r in rs])
        for r in rs:
            extra = ", ".join(
                f"{k}={short[r.settings.get(k, '<unset>')] if k == 'checkpoint' else r.settings.get(k, '<unset>')}"
                for k in varying
            )
            labels[r.path] = f"{name} ({extra})" if extra else name
    return labels


def _collect(
    runs: Sequence[EvalRun], metric: str, labels: Mapping[Path, str] | None = None, warn: Any = None
) -> dict[str, dict[str, dict[float, float]]]:
    """``{agent label: {difficulty: {threshold: metric value}}}`` of one group (``metric`` ``"stopped"``:
    1.0 when some episode ended by ``stop``, else 0.0). Two runs in one cell are reported to ``warn``
    (same settings twice: the later folder is shown)."""
    labels = labels or {r.path: r.agent for r in runs}
    table: dict[str, dict[str, dict[float, float]]] = {}
    source: dict[tuple[str, str, float], Path] = {}
    for run in runs:
        for d in run.difficulties():
            value = float(run.stopped(d)) if metric == "stopped" else run.summary[d].get(metric)
            if value is None:
                continue
            t = threshold_value(run.d_thresh, d)
            cell = (labels[run.path], d, t)
            if cell in source and warn is not None:
                warn(f"{source[cell]} and {run.path} have the same settings ({cell[0]}, {d}, d_thresh "
                     f"{format_threshold(t)}); the table shows {run.path}")
            source[cell] = run.path
            table.setdefault(labels[run.path], {}).setdefault(d, {})[t] = float(value)
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


def threshold_table(runs: Sequence[EvalRun], metric: str = "eps", warn: Any = None) -> str:
    """Markdown tables in the layout of the paper's Tables 13-15: one table per group of runs (see
    :func:`group_runs`: data set, split, FoV, view size, corruption, episodes, checkpoint, ...), rows
    difficulty x agent, columns the ``d_thresh`` values, cells ``metric`` (default ``eps``); the best
    value of each row among the runs that stopped in some episode is bold (lowest for ``eps``, highest
    otherwise; ties all bold). A run in which no episode ended by ``stop`` (``omega_stop`` 0: every
    episode ran to ``T``) is marked ``(no stop)`` and never bold: it is no candidate for ``d_thresh``."""
    lower_is_better = metric == "eps"
    out: list[str] = []
    for group in group_runs(runs, "thresholds"):
        labels = agent_labels(group.runs)
        data = _collect(group.runs, metric, labels, warn)
        stops = _collect(group.runs, "stopped", labels)
        if not data:
            continue
        thresholds = sorted({t for row in data.values() for d in row.values() for t in d})
        diffs = _order_difficulties(d for row in data.values() for d in row)
        out.append(f"## {group.title()}: {metric} per d_thresh (best in bold)")
        out.append("")
        out.append("| difficulty | agent | " + " | ".join(format_threshold(t) for t in thresholds) + " |")
        out.append("|---|---|" + "---|" * len(thresholds))
        for d in diffs:
            for label in sorted(data):
                row = data[label].get(d)
                if not row:
                    continue
                stopped = stops.get(label, {}).get(d, {})
                vals = [v for t, v in row.items() if not math.isnan(v) and stopped.get(t, 1.0)]
                best = (min(vals) if lower_is_better else max(vals)) if vals else None
                cells = []
                for t in thresholds:
                    if t not in row:
                        cells.append("-")
                        continue
                    s = _fmt_value(row[t], metric)
                    if not stopped.get(t, 1.0):
                        cells.append(s + " (no stop)")
                        continue
                    cells.append(f"**{s}**" if best is not None and row[t] == best else s)
                out.append(f"| {d} | {label} | " + " | ".join(cells) + " |")
        out.append("")
    if not out:
        return "(no finished runs with a summary)\n"
    return "\n".join(out)


def _best_of_group(group: RunGroup, warn: Any = None) -> dict[str, dict[str, float]]:
    """Per agent label and difficulty the best threshold among the runs that stopped in some episode; a
    row where no run stopped gets no threshold (said to ``warn``)."""
    labels = agent_labels(group.runs)
    eps, spl = _collect(group.runs, "eps", labels), _collect(group.runs, "spl", labels)
    stops = _collect(group.runs, "stopped", labels)
    best: dict[str, dict[str, float]] = {}
    for label, per_diff in eps.items():
        for d, row in per_diff.items():
            stopped = stops.get(label, {}).get(d, {})
            candidates = [t for t, v in row.items() if not math.isnan(v) and stopped.get(t, 1.0)]
            if not candidates and warn is not None:
                tried = ", ".join(format_threshold(t) for t in sorted(row))
                warn(f"{label} on {group.title()}, {d}: no run stopped in any episode (omega_stop 0 for d_thresh "
                     f"{tried}; every episode ran to T = {group.max_steps}): no d_thresh chosen for {d}")
            if candidates:
                s = spl.get(label, {}).get(d, {})
                best.setdefault(label, {})[d] = min(candidates, key=lambda t: (row[t], -s.get(t, 0.0), t))
    return best


def config_suffix(group: RunGroup) -> str:
    """A file-name tag for a group's distinguishing settings (``sim.fov=60`` -> ``fov60``), ``""`` if none."""
    parts = []
    for k, v in group.context:
        if k in ("split", "dataset.name"):
            continue
        v = re.sub(r"^(-?\d+)\.0$", r"\1", v)
        parts.append(k.split(".")[-1] + re.sub(r"[^A-Za-z0-9.-]+", "-", v).strip("-"))
    return "_".join(parts)


def tuned_thresholds(
    runs: Sequence[EvalRun], allow_test_tuning: bool = False, warn: Any = None
) -> dict[tuple[str, str, str], tuple[dict[str, float], RunGroup]]:
    """``{(agent label, dataset, suffix): ({difficulty: best d_thresh}, group)}``: per difficulty the lowest
    mean ``eps`` among the runs in which some episode ended by ``stop``; ties go to the higher SPL, then to
    the smaller threshold (tied thresholds give identical runs). A difficulty where no run stopped gets no
    threshold and an agent with none at all no entry (each said to ``warn``). Learned agents (a
    ``checkpoint``) have no threshold and are left out. ``suffix`` is ``""`` when the agent and data set have runs of one setting only, else
    :func:`config_suffix` of the group (one tuned config per FoV, view size, ...).

    Only validation-split runs are used; other splits only with ``allow_test_tuning``, and then only
    for agents and data sets without validation runs.

    Raises:
        CollectError: only non-validation runs and no ``allow_test_tuning``.
    """
    groups = group_runs([r for r in runs if not r.learned], "thresholds")
    val_groups = [g for g in groups if all(r.is_val for r in g.runs)]
    chosen = val_groups
    if allow_test_tuning:
        covered = {(r.agent, r.dataset) for g in val_groups for r in g.runs}
        chosen = val_groups + [g for g in groups if g not in val_groups and not {(r.agent, r.dataset) for r in g.runs} <= covered]
    elif not val_groups:
        splits = ", ".join(sorted({r.split for r in runs}))
        raise CollectError(
            f"refusing to tune d_thresh on split {splits} (the benchmark's held-out episodes): run the sweep with "
            "split=val, or pass allow_test_tuning=true (or write_config=false for the table only)"
        )
    picks: dict[tuple[str, str], list[tuple[dict[str, float], RunGroup]]] = {}
    for g in chosen:
        best = _best_of_group(g, warn)
        for label in sorted({lab for lab in agent_labels(g.runs).values()} - set(best)):
            if warn is not None:
                warn(f"{label} on {g.title()}: no run stopped in any episode; no d_thresh chosen, no config written")
        for label, thresholds in best.items():
            picks.setdefault((label, g.dataset), []).append((thresholds, g))
    out: dict[tuple[str, str, str], tuple[dict[str, float], RunGroup]] = {}
    for (label, dataset), found in picks.items():
        for thresholds, g in found:
            out[(label, dataset, config_suffix(g) if len(found) > 1 else "")] = (thresholds, g)
    return out


def best_thresholds(runs: Sequence[EvalRun], allow_test_tuning: bool = True) -> dict[tuple[str, str], dict[str, float]]:
    """``{(agent, dataset): {difficulty: best d_thresh}}`` for runs of one setting per agent and data set
    (see :func:`tuned_thresholds`; the validation runs decide when there are several splits).

    Raises:
        CollectError: an agent and data set with runs of several settings (use :func:`tuned_thresholds`).
    """
    out: dict[tuple[str, str], dict[str, float]] = {}
    for (label, dataset, suffix), (thresholds, group) in tuned_thresholds(runs, allow_test_tuning).items():
        if suffix:
            raise CollectError(f"{label} on {dataset} has runs of several settings ({group.title()}, ...)")
        out[(label, dataset)] = thresholds
    return out


def dataset_overrides(run_dir: Path) -> list[str]:
    """The ``dataset`` / ``dataset.*`` command-line overrides of a run (``.hydra/overrides.yaml``; [] when absent)."""
    from omegaconf import OmegaConf

    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return []
    items = OmegaConf.to_container(OmegaConf.load(path)) or []
    return [str(o) for o in items if isinstance(o, str) and (o.startswith("dataset=") or o.startswith("dataset."))]


def _yaml_number(x: float) -> str:
    if math.isinf(x):
        return ".inf"
    return str(int(x)) if float(x).is_integer() else repr(float(x))


def tuned_config_text(
    agent: str, dataset: str, thresholds: Mapping[str, float], source: str = "", split: str = "val",
    name: str | None = None, settings: str = "", untuned: Sequence[str] = (), dataset_args: Sequence[str] = (),
) -> str:
    """An ``agent`` group config that extends ``<agent>.yaml`` with the tuned ``d_thresh`` per difficulty,
    to be copied into ``configs/agent/``.

    Difficulties without a tuned value keep the base config's threshold. ``name``: the config's name
    (default ``<agent>_tuned_<dataset>``); ``settings``: the runs' distinguishing settings, for the header;
    ``untuned``: difficulties that were evaluated but where no run stopped (named in the header);
    ``dataset_args``: the tuning runs' data set overrides (``dataset=sun360_indoor dataset.root=...``), for the
    header's "Use it" line (``dataset`` is a data set's name, not a config of the ``dataset`` group).
    """
    name = name or f"{agent}_tuned_{dataset}"
    lines = [
        f"# {agent} with d_thresh tuned on the {dataset} {split} episodes (lowest mean eps per difficulty),",
        "# written by tools/collect_results.py" + (f" from {source}" if source else "") + ".",
        *([f"# Tuned for: {settings}"] if settings else []),
        *([f"# Not tuned (no run stopped in any episode; the base config's d_thresh stays): {', '.join(untuned)}"]
          if untuned else []),
        f"# Use it: cp {name}.yaml configs/agent/ && python tools/eval.py agent={name} "
        + (" ".join(dataset_args) if dataset_args else f"<the data set options of the runs that made {dataset}>"),
        "defaults:",
        f"  - {agent}",
        "  - _self_",
        "d_thresh:",
    ]
    for d in _order_difficulties(thresholds):
        lines.append(f"  {d}: {_yaml_number(thresholds[d])}")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ corruption tables
def corruption_columns(names: Iterable[str]) -> list[tuple[str, str]]:
    """``[(category, corruption)]`` in the paper's order: ``clear`` first, then blur, noise, digital,
    weather (each in its listed order), then unknown names under ``other`` (sorted)."""
    names = set(names)
    cols = [("", CLEAR)] if CLEAR in names else []
    known = set()
    for cat, members in CORRUPTION_CATEGORIES.items():
        for n in members:
            known.add(n)
            if n in names:
                cols.append((cat, n))
    cols += [("other", n) for n in sorted(names - known - {CLEAR})]
    return cols


def mean_over_difficulties(runs: Sequence[EvalRun], metric: str = "eps") -> tuple[float, bool]:
    """The mean over the difficulties of the per-difficulty means of ``metric`` found in ``runs``;
    the flag is ``True`` when all three of easy, medium and hard are present. ``nan`` when none."""
    per_diff: dict[str, float] = {}
    for r in runs:
        for d in r.difficulties():
            v = r.summary[d].get(metric)
            if v is not None:
                per_diff[d] = float(v)
    if not per_diff:
        return math.nan, False
    return sum(per_diff.values()) / len(per_diff), all(d in per_diff for d in DIFFICULTIES)


def corruption_table(runs: Sequence[EvalRun], metric: str = "eps", warn: Any = None) -> str:
    """Markdown tables in the layout of the paper's Tables 8-11: ``metric`` (default ``eps``) averaged
    over the three difficulties, one column per corruption grouped by category with ``clear`` first,
    one row per agent, one table per severity (and per group of otherwise different settings, see
    :func:`group_runs`). The clear runs (severity 0) fill the ``clear`` column of every severity's
    table. A value marked ``*`` lacks some difficulty."""
    out: list[str] = []
    for group in group_runs(runs, "corruption"):
        labels = agent_labels(group.runs, swept=())
        severities = sorted({r.severity for r in group.runs if r.corruption != CLEAR}) or [0]
        for sev in severities:
            in_table = [r for r in group.runs if r.corruption == CLEAR or r.severity == sev]
            cols = corruption_columns(r.corruption for r in in_table)
            rows = sorted({labels[r.path] for r in in_table})
            title = group.title()
            out.append(f"## {title}: {metric} averaged over the difficulties, severity {sev}")
            out.append("")
            out.append("| agent | " + " | ".join("clear" if c == CLEAR else c for _, c in cols) + " |")
            out.append("|---|" + "---|" * len(cols))
            if any(cat for cat, _ in cols):
                cats, prev = [], None
                for cat, _ in cols:
                    cats.append(f"*{cat}*" if cat and cat != prev else "")
                    prev = cat
                out.append("| *category* | " + " | ".join(cats) + " |")
            for label in rows:
                cells = []
                for _, c in cols:
                    cell_runs = [r for r in in_table if labels[r.path] == label and r.corruption == c]
                    dup: dict[str, Path] = {}
                    dup_summary: dict[str, Any] = {}
                    for r in cell_runs:
                        for d in r.difficulties():
                            # a severity sweep runs `none` once per severity: identical clear runs are no conflict
                            same_clear = c == CLEAR and d in dup and r.summary[d] == dup_summary.get(d)
                            if d in dup and warn is not None and not same_clear:
                                warn(f"{dup[d]} and {r.path} have the same settings ({label}, {c}, severity "
                                     f"{sev}, {d}); the table shows {r.path}")
                            dup[d] = r.path
                            dup_summary[d] = r.summary[d]
                    value, complete = mean_over_difficulties(cell_runs, metric)
                    s = _fmt_value(value, metric)
                    cells.append(s + ("*" if not complete and not math.isnan(value) else ""))
                out.append(f"| {label} | " + " | ".join(cells) + " |")
            out.append("")
    if not out:
        return "(no finished runs with a summary)\n"
    return "\n".join(out)
