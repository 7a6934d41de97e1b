"""tools/collect_results.py on synthetic multirun folders: runs that differ in a setting are never merged,
tuned configs only come from validation runs, and the corruption tables (paper Tables 8-11) average eps
over the difficulties in the paper's column order."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from _tools import load_tool
from findview_baselines.evaluation.results import (
    CORRUPTION_CATEGORIES,
    CollectError,
    corruption_of,
    corruption_table,
    dataset_overrides,
    find_runs,
    group_runs,
    threshold_table,
    tuned_config_text,
    tuned_thresholds,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def collect():
    """``tools/collect_results.py``'s ``main`` (in process: fast)."""
    return load_tool("collect_results").main


def metrics(eps: float, spl: float = 0.5, stop: float = 1.0) -> dict:
    return {"eps": eps, "omega_stop": stop, "omega_perf": 0.5, "spl": spl, "episodes": 4}


def fake_run(
    root: Path, name: str, eps: dict[str, float], agent: str = "orb", d_thresh=20, fov: int = 90, split: str = "val",
    difficulty: str | None = None, meta: dict | None = None, spl: dict[str, float] | None = None,
    stop: dict[str, float] | None = None, **extra,
) -> Path:
    """A finished tools/eval.py run folder: .hydra/config.yaml (JSON is YAML), summary.json, run.json."""
    d = root / name
    (d / ".hydra").mkdir(parents=True)
    cfg = {
        "agent": {"name": agent, "d_thresh": d_thresh, "threads": 4, **extra.pop("agent_extra", {})},
        "dataset": {"name": "toy", "out_dir": "/data/toy"},
        "sim": {"fov": fov, "height": 64, "width": 64, "device": "cpu"},
        "task": {"max_steps": extra.pop("max_steps", 5000)},
        "split": split, "difficulty": difficulty, "episodes": None, "seed": 0, "progress": False,
        "num_envs": extra.pop("num_envs", 16), **extra,
    }
    (d / ".hydra" / "config.yaml").write_text(json.dumps(cfg))
    summary = {k: metrics(v, (spl or {}).get(k, 0.5), (stop or {}).get(k, 1.0)) for k, v in eps.items()}
    summary["runtime"] = {"agent_fps": 1.0, "env_fps": 1.0}
    (d / "summary.json").write_text(json.dumps(summary))
    (d / "run.json").write_text(json.dumps({"agent": agent, "dataset": "toy", "split": split, **(meta or {})}))
    return d


def table_rows(text: str, title_part: str) -> list[str]:
    """The body rows of the markdown table whose title contains ``title_part``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## ") and title_part in line)
    rows = []
    for line in lines[start + 4 :]:
        if not line.startswith("|"):
            break
        rows.append(line)
    return rows


# ------------------------------------------------------------------------------ threshold layout
def test_fov_sweep_gives_one_table_per_fov(tmp_path, collect, capsys):
    """-m sim=fov90,fov60: the FoV 60 runs must not overwrite the FoV 90 cells."""
    for fov, base in ((90, 1.0), (60, 7.0)):
        fake_run(tmp_path, f"{fov}_a", {"easy": base}, d_thresh=20, fov=fov, num_envs=8)
        fake_run(tmp_path, f"{fov}_b", {"easy": base + 2}, d_thresh="inf", fov=fov)
    runs = find_runs(tmp_path)
    assert len(runs) == 4
    groups = group_runs(runs)
    assert [g.context for g in groups] == [(("sim.fov", "60"),), (("sim.fov", "90"),)]  # num_envs does not split
    text = threshold_table(runs)
    assert table_rows(text, "sim.fov=90") == ["| easy | orb | **1.00** | 3.00 |"]
    assert table_rows(text, "sim.fov=60") == ["| easy | orb | **7.00** | 9.00 |"]
    # one tuned config per FoV, named after it; out= (one file) cannot hold both: one line, status 2
    best = tuned_thresholds(runs)
    assert {k: v[0] for k, v in best.items()} == {("orb", "toy", "fov60"): {"easy": 20.0}, ("orb", "toy", "fov90"): {"easy": 20.0}}
    out = tmp_path / "tuned.yaml"
    assert collect([str(tmp_path), f"out={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "orb/toy/fov60" in err[0] and not out.exists()
    assert (tmp_path / "thresholds.md").is_file()  # the tables are still written
    assert collect([str(tmp_path), "write_config=false"]) == 0


def test_every_differing_setting_splits(tmp_path):
    """Corruption severity, checkpoint and episode file each tell tables apart; agent settings tell rows apart."""
    fake_run(tmp_path, "a", {"hard": 1.0}, meta={"corruption": "fog", "severity": 1})
    fake_run(tmp_path, "b", {"hard": 2.0}, meta={"corruption": "fog", "severity": 3})
    fake_run(tmp_path, "c", {"hard": 3.0}, meta={"corruption": "fog", "severity": 3}, agent_extra={"n_features": 1000})
    text = threshold_table(find_runs(tmp_path))
    assert table_rows(text, "severity=1") == ["| hard | orb | **1.00** |"]
    assert table_rows(text, "severity=3") == ["| hard | orb (agent.n_features=1000) | **3.00** |", "| hard | orb (agent.n_features=<unset>) | **2.00** |"]

    other = tmp_path / "ckpt"
    fake_run(other, "a", {"hard": 1.0}, agent="ppo", d_thresh=None, checkpoint="runs/a/best.pth")
    fake_run(other, "b", {"hard": 5.0}, agent="ppo", d_thresh=None, checkpoint="runs/b/best.pth")
    assert [g.context for g in group_runs(find_runs(other))] == [(("checkpoint", "runs/a/best.pth"),), (("checkpoint", "runs/b/best.pth"),)]


def test_a_null_setting_is_the_same_as_an_absent_one(tmp_path):
    """A run made before an optional field existed shares a table with a run that has it null; a set
    value still splits (a sweep that ran across a code update must not fall into two tables)."""
    fake_run(tmp_path, "old", {"hard": 1.0}, meta={"corruption": "fog", "severity": 3})
    fake_run(tmp_path, "new", {"hard": 2.0}, agent="sift", meta={"corruption": "fog", "severity": 3},
             corruption={"weights": None})
    assert [len(g.runs) for g in group_runs(find_runs(tmp_path))] == [2]
    fake_run(tmp_path, "weighted", {"hard": 3.0}, agent="rotation", meta={"corruption": "fog", "severity": 3},
             corruption={"weights": {"fog": 3}})
    groups = group_runs(find_runs(tmp_path))
    assert sorted(len(g.runs) for g in groups) == [1, 2]
    assert [g.context for g in groups if len(g.runs) == 1] == [(("corruption.weights.fog", "3"),)]


def test_tuned_config_names_the_runs_data_set_options(tmp_path, collect):
    """The tuned file's "Use it" line repeats the tuning runs' dataset overrides (a data set's name is not a
    config of the dataset group); without .hydra/overrides.yaml it says so instead of guessing."""
    run = fake_run(tmp_path, "0", {"easy": 1.0})
    (run / ".hydra" / "overrides.yaml").write_text(
        "- agent=orb\n- dataset=folder\n- dataset.root=/pics\n- dataset.name=toy\n- split=val\n- datasets_x=1\n")
    assert dataset_overrides(run) == ["dataset=folder", "dataset.root=/pics", "dataset.name=toy"]
    assert dataset_overrides(tmp_path / "missing") == []
    assert collect([str(tmp_path)]) == 0
    use = [line for line in (tmp_path / "orb_tuned_toy.yaml").read_text().splitlines() if "Use it" in line]
    assert use == ["# Use it: cp orb_tuned_toy.yaml configs/agent/ && python tools/eval.py agent=orb_tuned_toy "
                   "dataset=folder dataset.root=/pics dataset.name=toy"]
    assert "dataset=toy" not in tuned_config_text("orb", "toy", {"easy": 20.0})


def test_duplicate_cells_are_reported(tmp_path):
    fake_run(tmp_path, "0", {"easy": 1.0})
    fake_run(tmp_path, "1", {"easy": 4.0})
    warnings: list[str] = []
    text = threshold_table(find_runs(tmp_path), warn=warnings.append)
    assert len(warnings) == 1 and str(tmp_path / "0") in warnings[0] and str(tmp_path / "1") in warnings[0]
    assert table_rows(text, "toy / val") == ["| easy | orb | **4.00** |"]


def test_tuned_config_refuses_test_split(tmp_path, collect, capsys):
    fake_run(tmp_path, "0", {"easy": 3.0, "hard": 1.0}, d_thresh=10, split="test")
    fake_run(tmp_path, "1", {"easy": 2.0, "hard": 4.0}, d_thresh="inf", split="test")
    out = tmp_path / "orb_tuned.yaml"
    assert collect([str(tmp_path), f"out={out}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "split test" in err[0] and "allow_test_tuning=true" in err[0]
    assert not out.exists()
    with pytest.raises(CollectError):
        tuned_thresholds(find_runs(tmp_path))
    # asked explicitly: written, lowest eps per difficulty
    assert collect([str(tmp_path), f"out={out}", "--allow-test-tuning"]) == 0
    text = out.read_text()
    assert "easy: .inf" in text and "hard: 10" in text and "test episodes" in text


def test_validation_runs_decide(tmp_path, collect):
    """With val and test runs in one folder, the tuned config comes from val (whatever test says)."""
    fake_run(tmp_path, "v10", {"easy": 5.0}, d_thresh=10, split="val")
    fake_run(tmp_path, "v30", {"easy": 1.0}, d_thresh=30, split="val")
    fake_run(tmp_path, "t10", {"easy": 0.5}, d_thresh=10, split="test")
    fake_run(tmp_path, "t30", {"easy": 9.0}, d_thresh=30, split="test")
    best = tuned_thresholds(find_runs(tmp_path))
    assert {k: v[0] for k, v in best.items()} == {("orb", "toy", ""): {"easy": 30.0}}
    out = tmp_path / "t.yaml"
    assert collect([str(tmp_path), f"out={out}"]) == 0
    assert "easy: 30" in out.read_text()


def test_tie_on_eps_goes_to_higher_spl_then_smaller_threshold(tmp_path):
    fake_run(tmp_path, "0", {"easy": 2.0, "hard": 1.0}, d_thresh=10, spl={"easy": 0.2, "hard": 0.5})
    fake_run(tmp_path, "1", {"easy": 2.0, "hard": 1.0}, d_thresh=40, spl={"easy": 0.9, "hard": 0.5})
    best = tuned_thresholds(find_runs(tmp_path))
    assert best[("orb", "toy", "")][0] == {"easy": 40.0, "hard": 10.0}


# ------------------------------------------------------------------------------ corruption layout
def test_corruption_of_defaults_and_sources():
    assert corruption_of({}, {}) == ("none", 0)
    assert corruption_of({"corruption": {"name": "fog", "severity": 2}}, {}) == ("fog", 2)
    assert corruption_of({"corruption": {"name": "fog", "severity": 2}}, {"corruption": "snow", "severity": 5}) == ("snow", 5)
    assert corruption_of({"corruption": {"name": "none", "severity": 3}}, {}) == ("none", 0)


def test_corruption_tables(tmp_path, collect):
    """eps averaged over the difficulties (hand-computed), clear first, categories in the paper's order,
    one row per agent, one table per severity."""
    eps3 = lambda a, b, c: {"easy": a, "medium": b, "hard": c}  # noqa: E731
    fake_run(tmp_path, "orb_clear", eps3(1, 2, 3), meta={"corruption": "none"}, d_thresh={"easy": 10, "hard": 30})
    fake_run(tmp_path, "sift_clear", eps3(0, 0, 3), agent="sift", meta={"corruption": None})
    fake_run(tmp_path, "orb_fog1", eps3(2, 4, 6), meta={"corruption": "fog", "severity": 1}, d_thresh={"easy": 10, "hard": 30})
    fake_run(tmp_path, "orb_blur1", eps3(10, 20, 60), meta={"corruption": "motion_blur", "severity": 1}, d_thresh={"easy": 10, "hard": 30})
    fake_run(tmp_path, "sift_fog1", eps3(3, 3, 3), agent="sift", meta={"corruption": "fog", "severity": 1})
    fake_run(tmp_path, "orb_fog3", eps3(9, 9, 12), meta={"corruption": "fog", "severity": 3}, d_thresh={"easy": 10, "hard": 30})
    # sift under jpeg at severity 3: one run per difficulty, medium missing
    fake_run(tmp_path, "sift_jpeg3_e", {"easy": 4.0}, agent="sift", difficulty="easy", meta={"corruption": "jpeg_compression", "severity": 3})
    fake_run(tmp_path, "sift_jpeg3_h", {"hard": 8.0}, agent="sift", difficulty="hard", meta={"corruption": "jpeg_compression", "severity": 3})
    text = corruption_table(find_runs(tmp_path))
    lines = text.splitlines()
    i1 = lines.index(next(line for line in lines if "severity 1" in line))
    assert lines[i1 + 2] == "| agent | clear | motion_blur | fog |"  # clear, then blur before weather
    assert lines[i1 + 4] == "| *category* |  | *blur* | *weather* |"
    assert table_rows(text, "severity 1")[1:] == ["| orb | 2.00 | 30.00 | 4.00 |", "| sift | 1.00 | - | 3.00 |"]
    assert table_rows(text, "severity 3")[1:] == ["| orb | 2.00 | - | 10.00 |", "| sift | 1.00 | 6.00* | - |"]
    assert lines[next(i for i, line in enumerate(lines) if "severity 3" in line) + 2] == "| agent | clear | jpeg_compression | fog |"
    assert collect([str(tmp_path), "layout=corruption"]) == 0
    assert (tmp_path / "corruptions.md").read_text().count("## ") == 2


def test_corruption_column_order_is_the_papers():
    from findview_baselines.evaluation.results import corruption_columns

    names = [n for members in CORRUPTION_CATEGORIES.values() for n in members]
    cols = corruption_columns(list(reversed(names)) + ["none", "pixelate"])
    assert [c for _, c in cols] == ["none", *names, "pixelate"]
    assert [cat for cat, _ in cols[1:5]] == ["blur"] * 4 and cols[-1] == ("other", "pixelate")
    assert len(names) == 16


def test_cli_exit_status_in_a_subprocess(tmp_path):
    """The real command line: test-split tuning refused with status 2 and one line on stderr."""
    fake_run(tmp_path, "0", {"easy": 1.0}, split="test")
    proc = subprocess.run(
        [sys.executable, str(REPO / "tools" / "collect_results.py"), str(tmp_path), f"out={tmp_path / 'x.yaml'}"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "| easy | orb | **1.00** |" in proc.stdout


def test_clear_runs_of_a_severity_sweep_are_not_conflicts(tmp_path):
    """`corruption.name=none,... corruption.severity=1,3` runs the clear setting once per severity: equal
    results are the same cell (no warning); different results for the same settings are still reported."""
    eps3 = {"easy": 1.0, "medium": 2.0, "hard": 3.0}
    for name in ("0", "1"):
        fake_run(tmp_path / "same", name, eps3, meta={"corruption": "none", "severity": 0})
    fake_run(tmp_path / "same", "2", eps3, meta={"corruption": "fog", "severity": 1})
    warnings: list[str] = []
    text = corruption_table(find_runs(tmp_path / "same"), warn=warnings.append)
    assert warnings == []
    assert table_rows(text, "severity 1")[1:] == ["| orb | 2.00 | 2.00 |"]
    fake_run(tmp_path / "differ", "0", eps3, meta={"corruption": "none", "severity": 0})
    fake_run(tmp_path / "differ", "1", {**eps3, "hard": 9.0}, meta={"corruption": "none", "severity": 0})
    corruption_table(find_runs(tmp_path / "differ"), warn=warnings.append)
    assert len(warnings) == 1 and "hard" in warnings[0]


def test_learned_agents_are_rows_named_by_their_checkpoint(tmp_path):
    """Three checkpoints (with their own view size) and a rule-based agent land in one corruption table, the
    learned rows titled by their trainer and variant (never "ppo" for a DAgger-trained agent) and, where
    those are equal, labelled by the shortest distinct end of the checkpoint path."""
    eps3 = {"easy": 3.0, "medium": 3.0, "hard": 3.0}
    fake_run(tmp_path, "orb", eps3, meta={"corruption": "fog", "severity": 1})
    dagger = {"trainer": "dagger", "variant": "direct"}
    for name, ckpt, eps, info in (("a", "/runs/a/checkpoints/best.pth", 1.0, dagger),
                                  ("b", "/runs/b/checkpoints/best.pth", 2.0, dagger),
                                  ("c", "/runs/c/checkpoints/best.pth", 4.0, {"trainer": "ppo", "variant": "early_fusion"})):
        fake_run(tmp_path, name, {d: eps for d in eps3}, agent="ppo", checkpoint=ckpt,
                 meta={"corruption": "fog", "severity": 1, **info})
        cfg_path = tmp_path / name / ".hydra" / "config.yaml"
        cfg = json.loads(cfg_path.read_text())
        cfg["sim"]["height"] = cfg["sim"]["width"] = 32  # the learned agents' view size differs from orb's
        cfg_path.write_text(json.dumps(cfg))
    text = corruption_table(find_runs(tmp_path))
    assert text.count("## ") == 1
    assert table_rows(text, "severity 1")[1:] == [
        "| dagger direct (checkpoint=a/checkpoints/best.pth) | 1.00 |",
        "| dagger direct (checkpoint=b/checkpoints/best.pth) | 2.00 |",
        "| orb | 3.00 |",
        "| ppo early_fusion | 4.00 |",
    ]


# ------------------------------------------------------------------------------ runs that never stop
def test_runs_without_stops_are_never_picked(tmp_path, collect, capsys):
    """d_thresh=10 has the lowest eps but no episode stopped in it (every one ran to T): it is marked in the
    table and the config takes the best run that stopped; a difficulty where no run stopped is named on
    stderr and left out of the config."""
    fake_run(tmp_path, "10", {"easy": 1.0, "hard": 50.0}, d_thresh=10, stop={"easy": 0.0, "hard": 0.0}, max_steps=300)
    fake_run(tmp_path, "30", {"easy": 4.0, "hard": 60.0}, d_thresh=30, stop={"easy": 0.5, "hard": 0.0}, max_steps=300)
    fake_run(tmp_path, "inf", {"easy": 9.0, "hard": 70.0}, d_thresh="inf", stop={"easy": 1.0, "hard": 0.0}, max_steps=300)
    text = threshold_table(find_runs(tmp_path))
    assert "T = 300" in text.splitlines()[0]
    assert table_rows(text, "toy / val") == [
        "| easy | orb | 1.00 (no stop) | **4.00** | 9.00 |",
        "| hard | orb | 50.00 (no stop) | 60.00 (no stop) | 70.00 (no stop) |",
    ]
    assert collect([str(tmp_path)]) == 0
    out = capsys.readouterr()
    assert "hard" in out.err and "no run stopped" in out.err
    tuned = tmp_path / "orb_tuned_toy.yaml"  # into the sweep folder, never into the source tree
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(tuned)
    assert dict(cfg.d_thresh) == {"easy": 30} and "Not tuned" in tuned.read_text() and "hard" in tuned.read_text()
    assert "configs/agent/" in out.out


def test_no_run_stops_writes_no_config(tmp_path, collect, capsys):
    for t in (10, 20):
        fake_run(tmp_path, str(t), {"easy": float(t)}, d_thresh=t, stop={"easy": 0.0})
    assert tuned_thresholds(find_runs(tmp_path)) == {}
    assert collect([str(tmp_path)]) == 0
    out = capsys.readouterr()
    assert "no run stopped" in out.err and "no tuned config written" in out.out
    assert not list(tmp_path.glob("*.yaml"))
    assert (tmp_path / "thresholds.md").is_file()


def test_tuned_config_is_never_silently_overwritten(tmp_path, collect, capsys):
    fake_run(tmp_path, "a", {"easy": 1.0}, d_thresh=20)
    fake_run(tmp_path, "b", {"easy": 2.0}, d_thresh=40)
    assert collect([str(tmp_path)]) == 0
    tuned = tmp_path / "orb_tuned_toy.yaml"
    first = tuned.read_text()
    assert "easy: 20" in first
    assert collect([str(tmp_path)]) == 0 and tuned.read_text() == first  # same result: unchanged
    assert "(unchanged)" in capsys.readouterr().out
    tuned.write_text("# my edits\n")
    assert collect([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "overwrite=true" in err[0] and tuned.read_text() == "# my edits\n"
    assert collect([str(tmp_path), "overwrite=true"]) == 0 and tuned.read_text() == first


# ------------------------------------------------------------------------------ summary.md headers
def _fake_eval_dir(root: Path, overrides: list[str]) -> tuple[Path, str]:
    """A run folder as tools/eval.py leaves it before writing results: .hydra/hydra.yaml (config name and
    group choices) and the resolved config text."""
    from omegaconf import OmegaConf

    from findview_baselines.cli import compose_config

    cfg = compose_config("eval", overrides, return_hydra_config=True)
    (root / ".hydra").mkdir(parents=True)
    choices = {k: v for k, v in OmegaConf.to_container(cfg.hydra.runtime.choices).items()}
    OmegaConf.save({"hydra": {"job": {"config_name": "eval"}, "runtime": {"choices": choices}}}, root / ".hydra" / "hydra.yaml")
    plain = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    return root, OmegaConf.to_yaml(plain, resolve=True)


def test_summary_header_lists_every_non_default_setting(tmp_path):
    from findview_baselines.evaluation.results import run_settings, summary_markdown

    default_dir, default_cfg = _fake_eval_dir(tmp_path / "default", ["agent=sift"])
    changed_dir, changed_cfg = _fake_eval_dir(
        tmp_path / "changed", ["agent=sift", "agent.d_thresh=20", "sim=fov60", "task.max_steps=300", "progress=false"])
    assert run_settings(default_dir, default_cfg) == ["agent=sift"]  # orb is eval's default agent
    # the group choice once; its own values (sim.fov=60, height 192) are the defaults of fov60, not listed
    assert run_settings(changed_dir, changed_cfg) == [
        "agent=sift", "sim=fov60", "agent.d_thresh=20", "progress=false", "task.max_steps=300"]
    summary = {"easy": metrics(1.0), "runtime": {"agent_fps": 1.0, "env_fps": 1.0}}
    a = summary_markdown(summary, "sift", {"settings": run_settings(default_dir, default_cfg)})
    b = summary_markdown(summary, "sift", {"settings": run_settings(changed_dir, changed_cfg)})
    assert a != b and "`agent.d_thresh=20`" in b and "`task.max_steps=300`" in b


def test_learned_agent_summary_is_titled_by_trainer_and_variant():
    from findview_baselines.evaluation.results import summary_markdown

    summary = {"easy": metrics(1.0), "runtime": {"agent_fps": 1.0, "env_fps": 1.0}}
    meta = {"dataset": "toy", "split": "test", "checkpoint": "runs/q/checkpoints/best.pth", "trainer": "dagger", "variant": "direct"}
    assert summary_markdown(summary, "ppo", meta).splitlines()[0] == "# dagger direct on toy / test"
    assert summary_markdown(summary, "sift", {"dataset": "toy", "split": "test"}).splitlines()[0] == "# sift on toy / test"


def test_a_joblib_sweep_passes_the_tools_checks():
    """`-m hydra/launcher=joblib hydra.launcher.n_jobs=2 ...` (hydra-joblib-launcher, a requirement) composes
    and validates every job like the basic launcher (run_tool's pre-check returns instead of exiting)."""
    from findview_baselines.cli import compose_config, precheck

    argv = ["-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "agent=sift", "agent.d_thresh=20,inf", "split=val"]
    precheck("eval", "eval", argv)
    cfg = compose_config("eval", argv[1:3] + ["agent=sift", "agent.d_thresh=20"], return_hydra_config=True)
    assert "JoblibLauncher" in cfg.hydra.launcher._target_ and cfg.hydra.launcher.n_jobs == 2


def test_help_lists_no_schemas_or_tuned_files():
    """`--help` lists the config groups a user picks from: no schema entries (`base_ppo`, ...) and no
    tuned configs (collect_results writes those into the sweep folder, never into configs/)."""
    proc = subprocess.run([sys.executable, str(REPO / "tools" / "train.py"), "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    groups = proc.stdout.split("== Configuration groups ==")[1].split("== Config ==")[0]
    listed = {line.split(":")[0]: line.split(":", 1)[1] for line in groups.splitlines() if ":" in line and "(group=option)" not in line}
    assert {"agent", "dataset", "sim", "trainer"} <= set(listed)
    assert "base_" not in groups and "_tuned_" not in groups
    assert [o.strip() for o in listed["trainer"].split(",")] == ["dagger", "ppo"]
