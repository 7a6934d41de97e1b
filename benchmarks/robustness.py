"""The robustness benchmark in one command: agents x FoVs x corruptions x severities, resumable and parallel.

Every cell (agent, FoV, corruption, severity) is one ``tools/eval.py`` run (a subprocess with one torch
thread) into ``<out>/runs/<cell>/``; the clear targets run once per (agent, FoV). A cell whose
``summary.json`` exists and whose settings match is skipped, so re-running the same command resumes
(and re-runs only what changed). At the start the data set's episode files are made (``tools/make_dataset.py``
with ``force=false``: matching files are reused), each agent runs a short calibration (a few clean episodes,
one per difficulty, sequentially) and the expected run time is printed; at the end the wall time.

Output (``--out``)::

    runs/<agent>_fov<F>_<corruption>_s<severity>/   one tools/eval.py run per cell (+ robustness_cell.json,
    runs/<agent>_fov<F>_clear/                      robustness.log)
    calibration/                                    the timing runs and calibration.json
    data/<dataset>/                                 splits.json and episodes/ (unless --data-out is given)
    tables.md                                       the paper's Tables 8-11 layout: per FoV and severity,
                                                    eps and omega_stop, plus eps per corruption category
    plots/eps_vs_severity_fov<F>.png                eps against severity, one panel per category, one
                                                    line per agent (severity 0 = clear)
    benchmark.json                                  the plan, the estimate, the wall time, failed cells

Example (the issue's full setting; hours on a CPU)::

    python benchmarks/robustness.py --agents orb sift rotation checkpoint=pretrained/x.pth \\
        --dataset sun360_indoor --root $FINDVIEW_SUN360_MINI --dataset-name sun360_mini_indoor \\
        --episodes-per-image 10 --out outputs/robustness/sun360_mini_indoor
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
EVAL_TOOL = REPO / "tools" / "eval.py"
MAKE_DATASET_TOOL = REPO / "tools" / "make_dataset.py"
if str(Path(__file__).resolve().parent) not in sys.path:  # benchmarks/ (learning_curves' colours)
    sys.path.insert(0, str(Path(__file__).resolve().parent))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from findview.corruptions import CATEGORIES, NAMES  # noqa: E402
from findview.utils import atomic_write, write_json, write_text  # noqa: E402

CLEAR = "clear"
DIFFICULTIES = ("easy", "medium", "hard")
#: the agents of findview_baselines that have a config in configs/agent and need no checkpoint
BUILTIN_AGENTS = ("orb", "sift", "rotation", "random", "oracle")
#: plot geometry: 2 x 2 panels (one per corruption category) under a title band
PANEL_W, PANEL_H, TITLE_H = 480, 340, 36
PLOT_SIZE = (TITLE_H + 2 * PANEL_H, 2 * PANEL_W)  # (height, width) of every PNG


# --------------------------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class AgentSpec:
    """One row of the tables: a built-in agent config (``agent=<name>``) or a checkpoint."""

    key: str                    # cell-name prefix (orb, ckpt-<run>-<stem>)
    agent: str | None = None    # configs/agent/<agent>.yaml
    checkpoint: str | None = None  # absolute path

    def overrides(self) -> list[str]:
        return [f"checkpoint={hv(self.checkpoint)}"] if self.checkpoint else [f"agent={self.agent}"]


@dataclass
class Cell:
    """One tools/eval.py run."""

    name: str
    agent: AgentSpec
    fov: float
    corruption: str  # a corruption name or "clear"
    severity: int    # 0 for clear
    overrides: list[str]          # the settings (compared on resume)
    runtime: list[str] = field(default_factory=list)  # overrides that do not change results
    run_dir: Path = Path(".")
    kind: str = "cell"  # cell | calibration

    def spec(self, fingerprints: Mapping[str, str]) -> dict[str, Any]:
        spec: dict[str, Any] = {"tool": "tools/eval.py", "overrides": list(self.overrides)}
        if self.agent.checkpoint:
            spec["checkpoint_sha256"] = fingerprints.get(self.agent.checkpoint, "?")
        return spec


def hv(value: Any) -> str:
    """A value as a Hydra override value: bare when safe, else single-quoted."""
    s = str(value)
    if re.fullmatch(r"[A-Za-z0-9_./+:@~-]+", s):
        return s
    return "'" + s.replace("\\", "\\\\").replace("'", "\\'") + "'"


def fov_tag(fov: float) -> str:
    return f"{fov:g}"


def _sanitize(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "x"


def agent_config_names() -> list[str]:
    return sorted(p.stem for p in (REPO / "configs" / "agent").glob("*.yaml") if p.stem != "ppo")


def _agent_has_threads(name: str, seen: frozenset[str] = frozenset()) -> bool:
    """Whether configs/agent/<name>.yaml (or what it extends) has the ``threads`` key (feature agents)."""
    import yaml

    path = REPO / "configs" / "agent" / f"{name}.yaml"
    if name in seen or not path.is_file():
        return False
    doc = yaml.safe_load(path.read_text()) or {}
    if "threads" in doc:
        return True
    for entry in doc.get("defaults") or []:
        base = entry.split("@", 1)[0].lstrip("/") if isinstance(entry, str) else None  # "/base_feature@_here_"
        if base in ("base_feature", "base_rotation"):  # schemas with threads (their files need not restate it)
            return True
        if base is not None and not base.startswith("base_") and base != "_self_":
            if _agent_has_threads(base, seen | {name}):
                return True
    return False


def parse_agents(items: Sequence[str], error: Any) -> list[AgentSpec]:
    """``orb``, ``sift``, ``agent=<config>``, ``checkpoint=<path>`` -> agent specs (unique cell prefixes)."""
    names = agent_config_names()
    specs: list[AgentSpec] = []
    for item in items:
        if item.startswith("checkpoint="):
            path = os.path.abspath(os.path.expanduser(item.split("=", 1)[1]))
            if not os.path.isfile(path):
                error(f"checkpoint not found: {path}")
            p = Path(path)
            run = p.parent.parent.name if p.parent.name == "checkpoints" else p.parent.name
            specs.append(AgentSpec(key=_sanitize(f"ckpt-{run}-{p.stem}"), checkpoint=path))
        else:
            name = item.split("=", 1)[1] if item.startswith("agent=") else item
            if name not in names:
                error(f"unknown agent {item!r}: use one of {', '.join(names)} (configs/agent) or checkpoint=<path>")
            specs.append(AgentSpec(key=_sanitize(name), agent=name))
    seen: dict[str, int] = {}
    out = []
    for s in specs:  # two checkpoints with the same run / file name: add a hash of the path
        if s.key in seen or sum(1 for t in specs if t.key == s.key) > 1:
            digest = hashlib.sha1((s.checkpoint or s.agent or "").encode()).hexdigest()[:6]
            s = AgentSpec(key=f"{s.key}-{digest}", agent=s.agent, checkpoint=s.checkpoint)
        if s.key in seen:
            error(f"agent {s.checkpoint or s.agent} given twice")
        seen[s.key] = 1
        out.append(s)
    return out


def parse_corruptions(items: Sequence[str], error: Any) -> list[str]:
    """Names, categories (blur, noise, digital, weather), ``all``; in the paper's order."""
    wanted: set[str] = set()
    for item in items:
        for part in item.split(","):
            part = part.strip()
            if not part:
                continue
            if part == "all":
                wanted.update(NAMES)
            elif part in CATEGORIES:
                wanted.update(CATEGORIES[part])
            elif part in NAMES:
                wanted.add(part)
            elif part in (CLEAR, "none"):
                continue  # clear always runs unless --no-clear
            else:
                error(f"unknown corruption {part!r}: use all, a category ({', '.join(CATEGORIES)}) or one of {', '.join(NAMES)}")
    return [n for n in NAMES if n in wanted]


def dataset_overrides(args: argparse.Namespace) -> list[str]:
    """The data set passed through to tools/eval.py and tools/make_dataset.py."""
    out = [f"dataset={args.dataset}"]
    if args.root:
        out.append(f"dataset.root={hv(os.path.abspath(os.path.expanduser(args.root)))}")
    if args.dataset_name:
        out.append(f"dataset.name={hv(args.dataset_name)}")
    out.append(f"dataset.out_dir={hv(data_out_dir(args))}")
    out.append(f"dataset.episodes_per_image={args.episodes_per_image}")
    return out


def data_out_dir(args: argparse.Namespace) -> str:
    if args.data_out:
        return os.path.abspath(os.path.expanduser(args.data_out))
    return str(Path(args.out).resolve() / "data" / _sanitize(args.dataset_name or args.dataset))


def sim_override(agent: AgentSpec, fov: float, checkpoint_size: int | None = None) -> list[str]:
    """The cell's view: the rule-based agents take the FoV's preset (90: 256x256, 60: 256x192); a checkpoint
    brings its own view size unless ``checkpoint_size`` (pixels, square) is given: then it renders at that
    size and averages it down to its network's (a multiple of it)."""
    if agent.checkpoint is None:
        return [f"sim=fov{fov_tag(fov)}" if fov in (90.0, 60.0) else f"sim.fov={fov_tag(fov)}"]
    size = [f"sim.height={checkpoint_size}", f"sim.width={checkpoint_size}"] if checkpoint_size else []
    return [f"sim.fov={fov_tag(fov)}"] + size


def checkpoint_size_problems(agents: Sequence[AgentSpec], size: int | None) -> list[str]:
    """Why ``--checkpoint-size size`` cannot be rendered for a checkpoint: its network takes ``h x w`` and
    ``size x size`` is not ``k h x k w`` (empty: every checkpoint can)."""
    if size is None:
        return []
    from findview_baselines.rl.checkpoint import load_checkpoint
    from findview_baselines.rl.observations import downsample_factor

    out = []
    for a in agents:
        if a.checkpoint:
            sig = load_checkpoint(a.checkpoint, key="checkpoint")["signature"]
            h, w = int(sig["height"]), int(sig["width"])
            if downsample_factor((size, size), (h, w)) is None:
                hint = (f"a whole multiple of {h} (e.g. {4 * h})" if h == w else
                        "none: its views are not square (use --override sim.height=... --override sim.width=...)")
                out.append(f"--checkpoint-size {size}: checkpoint {a.checkpoint} takes {h}x{w} (height x width) "
                           f"views; expected {hint}")
    return out


def runtime_overrides(agent: AgentSpec, agent_threads: int, user: Sequence[str] = ()) -> list[str]:
    """The cell's thread settings; an ``agent.threads`` the user gave (``--override``) is kept."""
    from findview_baselines.evaluation.evaluate import override_keys

    out = ["progress=false", "torch_threads=1"]
    if agent.agent is not None and _agent_has_threads(agent.agent) and "agent.threads" not in override_keys(user):
        out.append(f"agent.threads={agent_threads}")
    return out


def make_plan(args: argparse.Namespace, agents: Sequence[AgentSpec], corruptions: Sequence[str]) -> list[Cell]:
    common = dataset_overrides(args) + [f"split={args.split}", f"task.max_steps={args.T}"]
    if args.max_episodes:
        common.append(f"max_episodes={args.max_episodes}")
    common += list(args.override or [])
    runs = Path(args.out).resolve() / "runs"
    threads = max(1, min(2, (os.cpu_count() or 1) // max(1, args.jobs)))
    cells: list[Cell] = []
    for agent in agents:
        for fov in args.fovs:
            base = agent.overrides() + sim_override(agent, fov, args.checkpoint_size) + common
            todo: list[tuple[str, int]] = ([] if args.no_clear else [(CLEAR, 0)])
            todo += [(c, s) for c in corruptions for s in args.severities]
            for corruption, sev in todo:
                if corruption == CLEAR:
                    name = f"{agent.key}_fov{fov_tag(fov)}_clear"
                    extra = ["corruption.name=none"]
                else:
                    name = f"{agent.key}_fov{fov_tag(fov)}_{corruption}_s{sev}"
                    extra = [f"corruption.name={corruption}", f"corruption.severity={sev}"]
                cells.append(Cell(name, agent, fov, corruption, sev, base + extra,
                                  runtime_overrides(agent, threads, args.override or []), runs / name))
    return cells


# ------------------------------------------------------------------------------------- resume / run
def checkpoint_fingerprints(agents: Sequence[AgentSpec]) -> dict[str, str]:
    out = {}
    for a in agents:
        if a.checkpoint:
            h = hashlib.sha256()
            with open(a.checkpoint, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
            out[a.checkpoint] = h.hexdigest()
    return out


def is_done(cell: Cell, fingerprints: Mapping[str, str]) -> bool:
    """``summary.json`` exists and ``robustness_cell.json`` holds the same settings."""
    if not (cell.run_dir / "summary.json").is_file():
        return False
    try:
        with open(cell.run_dir / "robustness_cell.json") as f:
            return json.load(f) == cell.spec(fingerprints)
    except (OSError, json.JSONDecodeError):
        return False


class Runner:
    """Runs tools/eval.py subprocesses; terminates the live ones on Ctrl-C / SIGTERM."""

    def __init__(self) -> None:
        self.live: set[subprocess.Popen] = set()
        self.lock = threading.Lock()
        self.stopping = False

    def run(self, cmd: list[str], log_path: Path | None = None) -> tuple[int, float, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        t0 = time.monotonic()
        with self.lock:
            if self.stopping:
                return 130, 0.0, "not started (interrupted)"
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
            self.live.add(proc)
        try:
            out, _ = proc.communicate()
        finally:
            with self.lock:
                self.live.discard(proc)
        wall = time.monotonic() - t0
        if log_path is not None:
            write_text(log_path, f"$ {' '.join(cmd)}\n{out}\n# exit {proc.returncode}, {wall:.1f} s\n")
        return proc.returncode, wall, out

    def stop(self) -> None:
        with self.lock:
            self.stopping = True
            for p in list(self.live):
                if p.poll() is None:
                    # SIGTERM, not SIGINT: a job started in the background of a shell ignores SIGINT, and so
                    # do its children. A stopped tools/eval.py has written no summary.json (written last,
                    # atomically), so the cell is simply run again on resume.
                    p.terminate()


def eval_command(cell: Cell) -> list[str]:
    return [sys.executable, str(EVAL_TOOL), *cell.overrides, *cell.runtime, f"hydra.run.dir={hv(cell.run_dir)}"]


def run_cell(runner: Runner, cell: Cell, fingerprints: Mapping[str, str]) -> tuple[int, float, str]:
    stale = cell.run_dir / "summary.json"
    if stale.exists():  # a finished run of other settings: it must not count as this cell's
        stale.unlink()
    write_json(cell.run_dir / "robustness_cell.json", cell.spec(fingerprints))
    return runner.run(eval_command(cell), cell.run_dir / "robustness.log")


def run_pool(runner: Runner, cells: Sequence[Cell], fingerprints: Mapping[str, str], jobs: int,
             report: Any = None) -> dict[str, tuple[int, float]]:
    """Run ``cells`` on ``jobs`` parallel subprocesses (in the given order); ``report(cell, rc, wall)`` as each
    ends. Ctrl-C / SIGTERM: the running jobs get SIGTERM (they write nothing), the others never start."""
    results: dict[str, tuple[int, float]] = {}
    pool = ThreadPoolExecutor(max_workers=max(1, min(jobs, len(cells))))
    pending: dict[Future, Cell] = {pool.submit(run_cell, runner, c, fingerprints): c for c in cells}
    try:
        while pending:
            ready, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in ready:
                c = pending.pop(fut)
                rc, wall, _ = fut.result()
                results[c.name] = (rc, wall)
                if report is not None:
                    report(c, rc, wall)
    except BaseException:
        runner.stop()
        for fut in pending:
            fut.cancel()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return results


# ------------------------------------------------------------------------------------ calibration
def episode_path(args: argparse.Namespace, fov: float) -> Path:
    return Path(data_out_dir(args)) / "episodes" / f"{args.split}_fov{fov_tag(fov)}.json"


def count_episodes(args: argparse.Namespace, fov: float) -> int | None:
    path = episode_path(args, fov)
    if not path.is_file():
        return None
    with open(path) as f:
        n = len(json.load(f).get("episodes", []))
    return min(n, args.max_episodes) if args.max_episodes else n


def calibration_cells(args: argparse.Namespace, agents: Sequence[AgentSpec], plan: Sequence[Cell]) -> list[Cell]:
    """Per agent: its clear cell's settings on ``--calibration-episodes`` episodes (the first ones of the
    difficulties in turn: easy, medium, hard, easy, ...), one environment, at the first FoV."""
    fov = args.fovs[0]
    src = episode_path(args, fov)
    calib_dir = Path(args.out).resolve() / "calibration"
    ep_file = calib_dir / f"episodes_{args.split}_fov{fov_tag(fov)}.json"
    if src.is_file():
        with open(src) as f:
            doc = json.load(f)
        by_diff = {d: [e for e in doc["episodes"] if e.get("difficulty") == d] for d in DIFFICULTIES}
        chosen = []
        for i in range(args.calibration_episodes):
            pool = by_diff[DIFFICULTIES[i % 3]]
            if i // 3 < len(pool):
                chosen.append(pool[i // 3])
        doc = {**doc, "episodes": chosen, "count": len(chosen),
               "difficulty_counts": {d: sum(e["difficulty"] == d for e in chosen) for d in DIFFICULTIES}}
        old = ep_file.read_text() if ep_file.is_file() else ""
        if old != json.dumps(doc, indent=1) + "\n":
            write_json(ep_file, doc)
    cells = []
    for agent in agents:
        ref = next(c for c in plan if c.agent == agent and c.fov == fov)
        keep = [o for o in ref.overrides if not o.startswith(("corruption.", "max_episodes="))]
        overrides = keep + ["corruption.name=none", f"episodes={hv(ep_file)}"]
        cells.append(Cell(f"{agent.key}", agent, fov, CLEAR, 0, overrides, ref.runtime + ["num_envs=1"],
                          calib_dir / agent.key, kind="calibration"))
    return cells


@dataclass
class Rate:
    """Measured cost of one agent: seconds per episode and per step, and the tool's start-up seconds."""

    s_per_episode: float
    s_per_step: float
    startup_s: float
    source: str

    def cell_seconds(self, episodes: int) -> float:
        return self.startup_s + episodes * self.s_per_episode

    def cell_seconds_max(self, episodes: int, T: int) -> float:
        return self.startup_s + episodes * T * self.s_per_step


def rate_from_run(run_dir: Path, process_wall: float | None) -> Rate | None:
    try:
        with open(run_dir / "run.json") as f:
            rt = json.load(f)["runtime"]
    except (OSError, KeyError, json.JSONDecodeError):
        return None
    loop = float(rt["wall_seconds"])
    eps, steps = max(1, int(rt["episodes"])), max(1, int(rt["env_steps"]))
    startup = max(0.0, process_wall - loop) if process_wall is not None else 4.0
    return Rate(loop / eps, loop / steps, startup, f"calibration: {eps} episodes, {steps} steps")


def fmt_duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    s = int(round(seconds))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def estimate(cells: Sequence[Cell], rates: Mapping[str, Rate], episodes: Mapping[float, int | None],
             T: int, jobs: int) -> tuple[float, float, list[str]]:
    """``(expected seconds, at-most seconds, lines per agent)`` for ``cells`` on ``jobs`` parallel jobs:
    the summed cell times over the jobs (but no less than the longest cell)."""
    per_agent: dict[str, list[float]] = {}
    total = total_max = longest = longest_max = 0.0
    for c in cells:
        rate, n = rates.get(c.agent.key), episodes.get(c.fov)
        if rate is None or n is None:
            return math.nan, math.nan, [f"  {c.agent.key}: no measured rate (or episode file) yet"]
        t, tm = rate.cell_seconds(n), rate.cell_seconds_max(n, T)
        total, total_max = total + t, total_max + tm
        longest, longest_max = max(longest, t), max(longest_max, tm)
        per_agent.setdefault(c.agent.key, [0, 0, 0.0])
        per_agent[c.agent.key][0] += 1
        per_agent[c.agent.key][1] += n
        per_agent[c.agent.key][2] += t
    lines = []
    for key, (ncells, neps, t) in per_agent.items():
        r = rates[key]
        lines.append(f"  {key}: {ncells} cells x {neps // max(1, ncells)} episodes x {r.s_per_episode:.2f} s/episode "
                     f"(+{r.startup_s:.1f} s start-up per cell; {1 / r.s_per_step:.0f} steps/s) = {fmt_duration(t)} "
                     f"of one core [{r.source}]")
    j = max(1, min(jobs, len(cells)))
    return max(total / j, longest), max(total_max / j, longest_max), lines


def rates_from_finished(cells: Sequence[Cell], startup: Mapping[str, Rate]) -> tuple[dict[str, Rate], int]:
    """Per agent, the :class:`Rate` of its finished ``cells`` (their ``run.json`` loop times, episodes and steps
    summed: what corrupted targets really cost, where the calibration measures clean episodes only), with the
    start-up seconds of ``startup`` (the calibration's) when known; and how many cells went into them."""
    totals: dict[str, list[float]] = {}
    for c in cells:
        try:
            with open(c.run_dir / "run.json") as f:
                rt = json.load(f)["runtime"]
            loop, eps, steps = float(rt["wall_seconds"]), int(rt["episodes"]), int(rt["env_steps"])
        except (OSError, KeyError, TypeError, ValueError):
            continue
        t = totals.setdefault(c.agent.key, [0.0, 0, 0, 0])
        t[0], t[1], t[2], t[3] = t[0] + loop, t[1] + eps, t[2] + steps, t[3] + 1
    rates = {}
    for key, (loop, eps, steps, n) in totals.items():
        start = startup[key].startup_s if key in startup else 4.0
        rates[key] = Rate(loop / max(1, eps), loop / max(1, steps), start, f"{int(n)} finished cells, {int(eps)} episodes")
    return rates, int(sum(t[3] for t in totals.values()))


# ------------------------------------------------------------------------------------ tables, plots
def _finished_runs(cells: Sequence[Cell], warn: Any) -> list[Any]:
    from findview_baselines.evaluation.results import find_runs

    root = cells[0].run_dir.parent
    if not root.is_dir():
        return []
    wanted = {c.run_dir.resolve() for c in cells}
    return [r for r in find_runs(root, warn=warn) if r.path.resolve() in wanted]


def category_means(runs: Sequence[Any], labels: Mapping[Path, str]) -> dict[str, dict[tuple[str, int], float]]:
    """``{agent label: {(category, severity): eps}}``: the mean over the category's corruptions of each
    corruption's eps (itself averaged over the difficulties); ``("clear", 0)`` for the clear targets."""
    from findview_baselines.evaluation.results import mean_over_difficulties

    cat_of = {n: cat for cat, names in CATEGORIES.items() for n in names}
    cells: dict[str, dict[tuple[str, int], list[float]]] = {}
    for r in runs:
        value, _ = mean_over_difficulties([r], "eps")
        if math.isnan(value):
            continue
        key = (CLEAR, 0) if r.corruption == "none" else (cat_of.get(r.corruption, "other"), r.severity)
        cells.setdefault(labels[r.path], {}).setdefault(key, []).append(value)
    return {a: {k: sum(v) / len(v) for k, v in d.items()} for a, d in cells.items()}


def category_table(means: Mapping[str, Mapping[tuple[str, int], float]], severities: Sequence[int]) -> str:
    cats = list(CATEGORIES)
    head = "| agent | clear | " + " | ".join(f"{c} s{s}" for c in cats for s in severities) + " |"
    lines = [head, "|---|---|" + "---|" * (len(cats) * len(severities))]
    for agent in sorted(means):
        m = means[agent]
        vals = [m.get((CLEAR, 0), math.nan)] + [m.get((c, s), math.nan) for c in cats for s in severities]
        lines.append(f"| {agent} | " + " | ".join("-" if math.isnan(v) else f"{v:.2f}" for v in vals) + " |")
    return "\n".join(lines) + "\n"


def plot_fov(means: Mapping[str, Mapping[tuple[str, int], float]], severities: Sequence[int], title: str, path: Path) -> Path:
    """One PNG: a panel per corruption category, eps (category mean) against severity (0 = clear), a line
    per agent."""
    from learning_curves import COLOURS  # benchmarks/learning_curves.py: the project's curve colours

    font = cv2.FONT_HERSHEY_SIMPLEX
    canvas = np.full((*PLOT_SIZE, 3), 255, np.uint8)
    cv2.putText(canvas, title, (10, 24), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    xs = [0, *sorted(severities)]
    values = [v for m in means.values() for v in m.values() if not math.isnan(v)]
    y1 = max(values) * 1.1 if values and max(values) > 0 else 1.0
    agents = sorted(means)
    left, right, top, bottom = 56, 20, 34, 44
    for k, cat in enumerate(CATEGORIES):
        ox, oy = (k % 2) * PANEL_W, TITLE_H + (k // 2) * PANEL_H
        x0p, x1p, y0p, y1p = ox + left, ox + PANEL_W - right, oy + PANEL_H - bottom, oy + top

        def px(x: float, y: float) -> tuple[int, int]:
            fx = (xs.index(x) / (len(xs) - 1)) if len(xs) > 1 else 0.5
            return int(x0p + fx * (x1p - x0p)), int(y0p - (y / y1) * (y0p - y1p))

        cv2.rectangle(canvas, (x0p, y1p), (x1p, y0p), (0, 0, 0), 1)
        cv2.putText(canvas, f"{cat}: eps (deg) vs severity", (x0p, oy + 22), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        for frac in (0.0, 0.5, 1.0):
            y = y1 * frac
            _, yp = px(xs[0], y)
            cv2.line(canvas, (x0p - 4, yp), (x0p, yp), (0, 0, 0), 1)
            cv2.putText(canvas, f"{y:.1f}", (ox + 4, yp + 4), font, 0.38, (0, 0, 0), 1, cv2.LINE_AA)
        for x in xs:
            xp, _ = px(x, 0)
            cv2.line(canvas, (xp, y0p), (xp, y0p + 4), (0, 0, 0), 1)
            label = "clear" if x == 0 else str(x)
            cv2.putText(canvas, label, (xp - 4 * len(label), y0p + 18), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(canvas, "severity", (x1p - 64, y0p + 36), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
        has_data = False
        for i, agent in enumerate(agents):
            colour = COLOURS[i % len(COLOURS)]
            m = means[agent]
            pts = [(x, m.get((CLEAR, 0) if x == 0 else (cat, x), math.nan)) for x in xs]
            pts = [px(x, y) for x, y in pts if not math.isnan(y)]
            has_data |= len(pts) > (1 if (CLEAR, 0) in m else 0)
            for a, b in zip(pts[:-1], pts[1:]):
                cv2.line(canvas, a, b, colour, 2, cv2.LINE_AA)
            for q in pts:
                cv2.circle(canvas, q, 3, colour, -1, cv2.LINE_AA)
            cv2.putText(canvas, agent[:40], (x0p + 6, y1p + 16 + 15 * i), font, 0.42, colour, 1, cv2.LINE_AA)
        if not has_data:
            cv2.putText(canvas, "(no corruption of this category run)", (x0p + 20, (y0p + y1p) // 2), font, 0.45,
                        (120, 120, 120), 1, cv2.LINE_AA)
    ok, data = cv2.imencode(".png", canvas)
    if not ok:
        raise RuntimeError(f"could not encode {path}")
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data.tobytes()))


def write_report(args: argparse.Namespace, cells: Sequence[Cell], header: Sequence[str]) -> tuple[Path, list[Path]]:
    """``tables.md`` (per FoV: eps and omega_stop per corruption and severity, eps per category) and one
    PNG per FoV."""
    from findview_baselines.evaluation.results import agent_labels, corruption_table

    warnings: list[str] = []
    runs = _finished_runs(cells, warnings.append)
    out = Path(args.out).resolve()
    lines = ["# Robustness benchmark", "", *header, ""]
    pngs: list[Path] = []
    for fov in args.fovs:
        fov_runs = [r for r in runs if float(r.settings.get("sim.fov", "nan")) == fov]
        lines += [f"## FoV {fov_tag(fov)}", ""]
        if not fov_runs:
            lines += ["(no finished runs)", ""]
            continue
        for metric, what in (("eps", "mean localization error, degrees (lower is better)"),
                             ("omega_stop", "share of episodes ended by the agent's stop")):
            lines += [f"### {metric}: {what}", ""]
            lines += [re.sub(r"(?m)^## ", "#### ", corruption_table(fov_runs, metric, warnings.append)), ""]
        labels = agent_labels(fov_runs, swept=())
        means = category_means(fov_runs, labels)
        lines += ["### eps per corruption category (mean over its corruptions), per severity", "",
                  category_table(means, args.severities)]
        png = out / "plots" / f"eps_vs_severity_fov{fov_tag(fov)}.png"
        pngs.append(png)
        plot_fov(means, args.severities, f"{args.dataset_name or args.dataset} / {args.split}, FoV {fov_tag(fov)}, "
                 f"T = {args.T}: eps vs severity (0 = clear)", png)
        lines += [f"![eps against severity, FoV {fov_tag(fov)}](plots/{png.name})", ""]
    if warnings:
        lines += ["## Warnings", "", *[f"- {w}" for w in warnings], ""]
    path = write_text(out / "tables.md", "\n".join(lines))
    return path, pngs


# ------------------------------------------------------------------------------------------- main
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python benchmarks/robustness.py",
        description="The robustness benchmark (the paper's Tables 8-11) in one command: every (agent, FoV, "
                    "corruption, severity) cell is one tools/eval.py run under <out>/runs/; finished cells are "
                    "skipped (resume); jobs run in parallel; the expected run time is printed first, the wall "
                    "time last; <out>/tables.md and <out>/plots/*.png are written at the end.",
        epilog="Example: python benchmarks/robustness.py --agents orb sift rotation --dataset sun360_indoor "
               "--root $FINDVIEW_SUN360_MINI --dataset-name sun360_mini_indoor --episodes-per-image 10 "
               "--out outputs/robustness/sun360_mini_indoor   (add --dry-run to see the plan only)",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--agents", nargs="+", default=["orb", "sift", "rotation"], metavar="AGENT",
                   help="agent configs (configs/agent: orb, sift, rotation, random, oracle, tuned configs) and any "
                        "number of learned agents as checkpoint=<path> (its view size comes from the checkpoint)")
    p.add_argument("--corruptions", nargs="+", default=["all"], metavar="NAME",
                   help="corruption names, categories (blur, noise, digital, weather) or all; the clear targets "
                        "run too (once per agent and FoV) unless --no-clear")
    p.add_argument("--no-clear", action="store_true", help="do not run the clear (uncorrupted) targets")
    p.add_argument("--severities", nargs="+", type=int, default=[1, 3, 5], help="corruption severities (1-5)")
    p.add_argument("--dataset", default="synthetic", help="data set config (configs/dataset): synthetic, "
                   "sun360_indoor, sun360_outdoor, indoor360, folder")
    p.add_argument("--root", default=None, help="dataset.root: the folder of the panoramas")
    p.add_argument("--dataset-name", default=None, help="dataset.name (names the data set in the tables)")
    p.add_argument("--data-out", default=None,
                   help="dataset.out_dir: splits.json and the episode files (default <out>/data/<name>; pointing "
                        "it at a shared folder made with another --episodes-per-image rewrites its episode files)")
    p.add_argument("--episodes-per-image", type=int, default=1, help="dataset.episodes_per_image (per difficulty)")
    p.add_argument("--split", default="test", help="split whose static episodes are run")
    p.add_argument("--fovs", nargs="+", type=float, default=[90.0, 60.0], help="fields of view (degrees)")
    p.add_argument("--T", "--max-steps", dest="T", type=int, default=5000, help="task.max_steps")
    p.add_argument("--max-episodes", type=int, default=None, help="max_episodes: only the first N episodes per cell")
    p.add_argument("--checkpoint-size", type=int, default=None, metavar="PIXELS",
                   help="render the checkpoints' views at PIXELS x PIXELS (a multiple of the network's size, which "
                        "the agent averages down to): 256 gives a 64x64 learned agent the targets the rule-based "
                        "agents see at FoV 90 (a corruption's kernel is in pixels); default: the checkpoint's own size")
    p.add_argument("--override", action="append", metavar="KEY=VALUE",
                   help="an extra tools/eval.py override for every cell (repeatable), e.g. --override dataset.hard_rule=and; "
                        "dataset.* overrides also go to the data set step (tools/make_dataset.py)")
    p.add_argument("--out", default="outputs/robustness", help="output folder")
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="parallel tools/eval.py jobs")
    p.add_argument("--calibration-episodes", type=int, default=2,
                   help="clean episodes per agent timed before the benchmark (easy, medium, hard, ... in turn); "
                        "0: no calibration (no estimate)")
    p.add_argument("--dry-run", action="store_true", help="print the plan, the commands and the estimate; run nothing")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.jobs < 1:
        parser.error("--jobs must be >= 1")
    if any(s not in (1, 2, 3, 4, 5) for s in args.severities):
        parser.error("--severities must be in 1..5")
    if args.T < 1 or args.episodes_per_image < 1 or args.calibration_episodes < 0:
        parser.error("--T and --episodes-per-image must be >= 1, --calibration-episodes >= 0")
    if args.checkpoint_size is not None and args.checkpoint_size < 1:
        parser.error(f"--checkpoint-size must be a positive number of pixels, got {args.checkpoint_size}")
    args.severities = sorted(set(args.severities))
    args.fovs = list(dict.fromkeys(float(f) for f in args.fovs))
    agents = parse_agents(args.agents, parser.error)
    if args.checkpoint_size is not None and not any(a.checkpoint for a in agents):
        print(f"robustness: --checkpoint-size {args.checkpoint_size} is ignored: no checkpoint among the agents",
              file=sys.stderr)
    for problem in checkpoint_size_problems(agents, args.checkpoint_size):
        parser.error(problem)
    corruptions = parse_corruptions(args.corruptions, parser.error)
    if not corruptions and args.no_clear:
        parser.error("nothing to run: no corruption and --no-clear")
    out = Path(args.out).resolve()
    plan = make_plan(args, agents, corruptions)
    fingerprints = checkpoint_fingerprints(agents)
    done = [c for c in plan if is_done(c, fingerprints)]
    todo = [c for c in plan if c not in done]
    print(f"robustness: {len(plan)} cells ({len(agents)} agents x {len(args.fovs)} FoVs x "
          f"({len(corruptions)} corruptions x {len(args.severities)} severities{'' if args.no_clear else ' + clear'})); "
          f"{len(done)} finished, {len(todo)} to run; {args.jobs} jobs; output {out}", flush=True)
    t_start = time.monotonic()
    runner = Runner()
    def on_sigterm(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    prev_term = signal.signal(signal.SIGTERM, on_sigterm)
    try:
        return _run(args, agents, plan, todo, done, fingerprints, runner, t_start)
    except KeyboardInterrupt:
        runner.stop()
        print("robustness: interrupted; finished cells are kept, re-run the same command to resume", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, prev_term)


def _run(args: argparse.Namespace, agents: Sequence[AgentSpec], plan: list[Cell], todo: list[Cell], done: list[Cell],
         fingerprints: Mapping[str, str], runner: Runner, t_start: float) -> int:
    out = Path(args.out).resolve()
    # the data set step gets the dataset.* overrides too (the cells' episode files must be made with them)
    dataset_extra = [o for o in (args.override or []) if o.split("=", 1)[0].lstrip("+~").startswith("dataset.")]
    make_cmd = [sys.executable, str(MAKE_DATASET_TOOL), *dataset_overrides(args), *dataset_extra,
                f"dataset.episode_fovs=[{','.join(fov_tag(f) for f in args.fovs)}]", f"sim.fov={fov_tag(args.fovs[0])}",
                "force=false", "progress=false"]
    calib_file = out / "calibration" / "calibration.json"
    rates: dict[str, Rate] = {}
    if calib_file.is_file():
        with open(calib_file) as f:
            saved = json.load(f)
        rates = {k: Rate(**v) for k, v in saved.get("rates", {}).items()}
    if args.dry_run:
        print("dry run: nothing is run. The data set step:\n  " + " ".join(make_cmd))
        for c in plan:
            print(f"  {'skip' if c in done else 'run '} {c.name}: " + " ".join(eval_command(c)[1:]))
        episodes = {f: count_episodes(args, f) for f in args.fovs}
        exp, most, lines = estimate(todo, rates, episodes, args.T, args.jobs)
        if todo:
            if math.isnan(exp):
                print("expected run time: not known before the calibration (a real run measures each agent first)")
            else:
                print(f"expected run time (earlier calibration): {fmt_duration(exp)}; at most {fmt_duration(most)}")
                print("\n".join(lines))
        return 0
    if todo:
        print("data set: " + " ".join(make_cmd[1:]), flush=True)
        rc, wall, text = runner.run(make_cmd, out / "logs" / "make_dataset.log")
        if rc != 0:
            print(f"robustness: making the data set failed (exit {rc}):\n{text[-3000:]}", file=sys.stderr)
            return 2 if rc == 2 else 1
    episodes = {f: count_episodes(args, f) for f in args.fovs}
    jobs = max(1, args.jobs)
    if todo and args.calibration_episodes > 0:
        calib = calibration_cells(args, agents, plan)
        need = [c for c in calib if not (c.agent.key in rates and is_done(c, fingerprints))]
        if need:
            print(f"calibration: {len(need)} agents x {args.calibration_episodes} clean episodes, one environment ...", flush=True)
            results = run_pool(runner, need, fingerprints, jobs)
            for c in need:
                rc, wall = results[c.name]
                rate = rate_from_run(c.run_dir, wall) if rc == 0 else None
                if rate is None:
                    log = c.run_dir / "robustness.log"
                    tail = log.read_text()[-2000:] if log.is_file() else ""
                    print(f"robustness: calibration of {c.agent.key} failed (exit {rc}); log: {log}\n{tail}", file=sys.stderr)
                    return 2 if rc == 2 else 1
                rates[c.agent.key] = rate
            write_json(calib_file, {"rates": {k: vars(v) for k, v in rates.items()}})
    exp, most, lines = estimate(todo, rates, episodes, args.T, jobs)
    if todo:
        print(f"expected run time: {fmt_duration(exp)} for {len(todo)} cells on {jobs} jobs "
              f"(clean-episode rates; at most {fmt_duration(most)} if every episode runs to T = {args.T})")
        if lines:
            print("\n".join(lines), flush=True)
        finished, n_finished = rates_from_finished(done, rates)
        if todo and all(c.agent.key in finished for c in todo):
            exp_f, most_f, lines_f = estimate(todo, finished, episodes, args.T, jobs)
            print(f"expected from the {n_finished} finished cells of these agents (corrupted targets included): "
                  f"{fmt_duration(exp_f)}; at most {fmt_duration(most_f)}")
            print("\n".join(lines_f), flush=True)
    t_cells = time.monotonic()
    failed: list[tuple[Cell, int]] = []
    if todo:
        # longest cells first (fewer idle jobs at the end)
        order = sorted(todo, key=lambda c: -(rates[c.agent.key].cell_seconds(episodes.get(c.fov) or 1)
                                             if c.agent.key in rates else 0.0))
        counter = [0]

        def report(c: Cell, rc: int, wall: float) -> None:
            counter[0] += 1
            ok = rc == 0 and (c.run_dir / "summary.json").is_file()
            if not ok:
                failed.append((c, rc))
            print(f"[{counter[0]}/{len(todo)}] {c.name}: {'done' if ok else f'FAILED (exit {rc})'} in {wall:.0f} s "
                  f"(elapsed {fmt_duration(time.monotonic() - t_cells)})", flush=True)

        run_pool(runner, order, fingerprints, jobs, report)
    wall_total = time.monotonic() - t_start
    history: list[dict[str, Any]] = []
    if (out / "benchmark.json").is_file():
        try:
            history = list(json.loads((out / "benchmark.json").read_text()).get("invocations", []))
        except (OSError, json.JSONDecodeError, AttributeError):
            history = []
    history.append({
        "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(time.time() - wall_total)),
        "argv": sys.argv[1:], "ran": len(todo), "skipped": len(done), "failed": len(failed), "jobs": jobs,
        "expected_s": None if math.isnan(exp) or not todo else round(exp, 1), "wall_s": round(wall_total, 1),
    })
    worked = [h for h in history if h["ran"]]
    header = [
        f"Data set `{args.dataset_name or args.dataset}` (`dataset={args.dataset}`), split `{args.split}`, "
        f"`dataset.episodes_per_image={args.episodes_per_image}`, T = {args.T}"
        + (f", max_episodes {args.max_episodes}" if args.max_episodes else "")
        + f"; episodes per cell: {', '.join(f'FoV {fov_tag(f)}: {n}' for f, n in episodes.items())}.",
        f"{len(plan)} cells. Wall time of the invocations that ran cells (data set, calibration and cells): "
        + ("; ".join(f"{h['started']}: {h['ran']} cells on {h['jobs']} jobs in {fmt_duration(h['wall_s'])}"
                     + (f" (expected {fmt_duration(h['expected_s'])})" if h.get("expected_s") is not None else "")
                     for h in worked) or "none")
        + (f"; total {fmt_duration(sum(h['wall_s'] for h in worked))}." if len(worked) > 1 else "."),
        "Values are means over the difficulties (a `*`: some difficulty missing); the clear column is the same "
        "run in every severity's table.",
    ]
    tables, pngs = write_report(args, plan, header)
    write_json(out / "benchmark.json", {
        "cells": len(plan), "ran": len(todo), "skipped": len(done),
        "failed": [{"cell": c.name, "exit": rc, "log": str(c.run_dir / "robustness.log")} for c, rc in failed],
        "rates": {k: vars(v) for k, v in rates.items()}, "invocations": history,
    })
    print(f"tables: {tables}")
    for png in pngs:
        print(f"plot: {png}")
    print(f"wall time: {fmt_duration(wall_total)} ({len(todo)} cells run, {len(done)} skipped"
          + (f"; expected {fmt_duration(exp)}" if todo and not math.isnan(exp) else "") + ")")
    if failed:
        print(f"robustness: {len(failed)} cells failed: " + ", ".join(f"{c.name} (log {c.run_dir / 'robustness.log'})"
                                                                       for c, _ in failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
