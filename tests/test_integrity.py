"""Data integrity and user errors of the tools (issue 16): data made from another root or other settings
is refused with one line and exit 2; a file with more episodes per image serves its first K; unwritable
output folders and unusable checkpoints are one line and exit 2; ``checkpoint=`` implies the learned agent."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from _tools import load_tool

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
SMALL = ["sim.height=64", "sim.width=64", "progress=false"]


def run_tool(tool: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}
    env.pop("FINDVIEW_DEBUG", None)
    return subprocess.run([PY, str(REPO / "tools" / tool), *args], capture_output=True, text=True, cwd=REPO,
                          timeout=timeout, env=env)


def one_error_line(proc: subprocess.CompletedProcess, tool: str) -> str:
    """The single stderr line of a refused command (exit 2)."""
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, f"exit {proc.returncode}\nstdout:\n{proc.stdout}\nstderr:\n{proc.stderr}"
    assert lines[0].startswith(f"{tool}: error: ")
    return lines[0]


def prepare_dataset(cfg, *args, **kwargs):
    """:func:`findview.dataset.prepare_dataset` of a mapping (converted once, like any caller outside the tools)."""
    from findview.config import DatasetConfig, as_section
    from findview.dataset import prepare_dataset as prepare

    return prepare(as_section(cfg, DatasetConfig), *args, **kwargs)


def ensure_dataset(cfg, *args, **kwargs):
    """:func:`findview.dataset.ensure_dataset` of a mapping (converted once with as_section)."""
    from findview.config import DatasetConfig, as_section
    from findview.dataset import ensure_dataset as ensure

    return ensure(as_section(cfg, DatasetConfig), *args, **kwargs)


def synthetic_cfg(base: Path, out: str, k: int) -> dict:
    return {"name": "synthetic", "kind": "synthetic", "root": str(base / "images"), "out_dir": str(base / out),
            "num_images": 4, "width": 256, "split": [0, 0, 1], "episodes_per_image": k, "episode_fovs": [90],
            "splits_to_make": ["test"], "validate": False}


def overrides(cfg: dict) -> list[str]:
    return [f"dataset.root={cfg['root']}", f"dataset.out_dir={cfg['out_dir']}", "dataset.num_images=4",
            "dataset.width=256", "dataset.split=[0,0,1]", "dataset.episode_fovs=[90]", "dataset.splits_to_make=[test]"]


@pytest.fixture(scope="module")
def k3(tmp_path_factory) -> dict:
    """A synthetic data set (4 images, all test) made with 3 episodes per image per difficulty."""
    base = tmp_path_factory.mktemp("integrity")
    cfg = synthetic_cfg(base, "k3", 3)
    prepare_dataset(cfg, [90], progress=False)
    return cfg


# ------------------------------------------------------------------------------------------------
# Episodes per image: a file with more serves its first K, equal to the file made with K
# ------------------------------------------------------------------------------------------------


def test_first_k_episodes_of_a_bigger_file_are_the_file_made_with_k(k3, tmp_path):
    from findview.dataset import DatasetError, episode_file, load_episodes

    big = episode_file(k3["out_dir"], "test", 90)
    for k in (1, 2):
        small_cfg = {**k3, "out_dir": str(tmp_path / f"k{k}"), "episodes_per_image": k}
        made = load_episodes(episode_file(prepare_dataset(small_cfg, [90], progress=False).out_dir, "test", 90))
        assert len(made) == 3 * 4 * k
        # a tool asking for k accepts the K=3 folder (nothing rewritten) and reads exactly the k-file's episodes
        stamp = big.stat().st_mtime_ns
        out = ensure_dataset({**k3, "episodes_per_image": k}, [90], pitch_bound=60, progress=False)
        assert big.stat().st_mtime_ns == stamp
        assert load_episodes(episode_file(out, "test", 90), episodes_per_image=k) == made
    assert len(load_episodes(big)) == 3 * 4 * 3
    with pytest.raises(DatasetError, match="episodes_per_image"):
        load_episodes(big, episodes_per_image=4)
    # a tool asking for more extends the nested file: the 3 episodes per image it held stay the first ones
    held = load_episodes(big)
    ensure_dataset({**k3, "episodes_per_image": 4}, [90], pitch_bound=60, progress=False)
    assert len(load_episodes(big)) == 3 * 4 * 4
    assert load_episodes(big, episodes_per_image=3) == held
    # a file that differs in another setting is still refused
    with pytest.raises(DatasetError, match="episode_seed"):
        ensure_dataset({**k3, "episodes_per_image": 5, "episode_seed": 99}, [90], pitch_bound=60, progress=False)


@pytest.mark.parametrize("tool", ["render_episode", "render_corruptions"])
def test_render_tools_use_a_bigger_file_under_their_own_logger(tool, k3, tmp_path, caplog):
    """Default episodes_per_image (1) on a K=3 folder: the tool renders episode 0 and logs as itself."""
    import logging

    from findview_baselines.cli import compose_config

    args = [*overrides(k3), *SMALL[:2]]
    cfg = compose_config(tool, args)
    with caplog.at_level(logging.INFO):
        png = load_tool(tool).render(cfg, tmp_path, {"dataset": "synthetic"}, args)
    assert png.is_file() and png.stat().st_size > 0
    names = {r.name for r in caplog.records}
    assert f"findview.{tool}" in names and "findview.eval" not in names
    assert any("reusing" in r.getMessage() and r.name == f"findview.{tool}" for r in caplog.records)


def test_checkpoint_eval_without_agent_ppo_uses_a_bigger_file_and_prints_the_table(k3, tmp_path):
    """eval with checkpoint= and a learned-agent key (no agent=ppo) on a K=3 folder with the default K=1
    runs, evaluates 1 episode per image, and prints its result table."""

    from findview_baselines.rl.policy import Policy

    torch.manual_seed(0)
    policy = Policy(64, 64, "early_fusion", hidden_size=32)
    ckpt = tmp_path / "tiny.pth"
    torch.save({"signature": policy.model_signature(), "policy": policy.state_dict(), "update": 0}, ckpt)
    run = tmp_path / "eval"
    proc = run_tool("eval.py", f"checkpoint={ckpt}", "agent.revisit_penalty=0", *overrides(k3), *SMALL,
                    "task.max_steps=20", "difficulty=easy", "num_envs=4", f"hydra.run.dir={run}")
    assert proc.returncode == 0, proc.stderr
    table = (run / "summary.md").read_text().strip()
    assert "| difficulty | episodes |" in table and table in proc.stdout
    assert "| easy | 4 |" in table  # 4 images x 1 episode (not the 12 of the file)


# ------------------------------------------------------------------------------------------------
# Data from another root: one line, exit 2, the make_dataset command
# ------------------------------------------------------------------------------------------------


def test_eval_refuses_synthetic_data_made_from_another_root(k3, tmp_path):
    wrong = tmp_path / "nowhere"
    args = [a if not a.startswith("dataset.root=") else f"dataset.root={wrong}" for a in overrides(k3)]
    proc = run_tool("eval.py", "agent=random", *args, *SMALL, "max_episodes=2", f"hydra.run.dir={tmp_path / 'run'}")
    line = one_error_line(proc, "eval")
    assert "splits.json was made for other dataset settings" in line and f"'{wrong}' now" in line
    assert f"python tools/make_dataset.py dataset=synthetic dataset.root={wrong}" in line
    assert not (tmp_path / "run").exists() and not wrong.exists()


def test_eval_refuses_sun360_data_made_from_another_root(sun360_mini, tmp_path):
    """The check eval (and the render tools) run before loading episodes (resolve_episodes), in-process."""
    from findview.dataset import DatasetError
    from findview_baselines.cli import compose_config, validate_config
    from findview_baselines.evaluation.evaluate import resolve_episodes

    cfg = {"name": "sun360_indoor", "kind": "sun360", "root": str(sun360_mini), "subset": "indoor",
           "out_dir": str(tmp_path / "data"), "split": [0, 0, 1], "episode_fovs": [90], "splits_to_make": ["test"],
           "validate": False}
    prepare_dataset(cfg, [90], progress=False)
    args = ["dataset=sun360_indoor", f"dataset.out_dir={cfg['out_dir']}", "dataset.split=[0,0,1]", "progress=false"]
    episodes, _, _ = resolve_episodes(validate_config(compose_config("eval", [*args, f"dataset.root={sun360_mini}"])),
                                      "sun360_indoor")
    assert len(episodes) > 0
    wrong = tmp_path / "SUN360"
    with pytest.raises(DatasetError) as info:
        resolve_episodes(validate_config(compose_config("eval", [*args, f"dataset.root={wrong}"])), "sun360_indoor")
    line = str(info.value)
    assert "\n" not in line and f"root '{sun360_mini}' in the file, '{wrong}' now" in line
    assert f"python tools/make_dataset.py dataset=sun360_indoor dataset.root={wrong}" in line


# ------------------------------------------------------------------------------------------------
# Unwritable output folders: one line, exit 2, in every tool (the shared pre-check)
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("config", ["eval", "make_dataset", "render_episode", "render_corruptions"])
def test_unwritable_run_folder_is_one_line(config, tmp_path, capsys):
    from findview_baselines.cli import precheck

    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for folder in ("/proc/findview_x", a_file / "run"):
        with pytest.raises(SystemExit) as exit_info:
            precheck(config, config, [f"hydra.run.dir={folder}"], check_run_dir=True)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"{config}: error: run folder (hydra.run.dir) {folder} is not writable")
    precheck(config, config, [f"hydra.run.dir={tmp_path / 'new' / 'run'}"], check_run_dir=True)
    assert not (tmp_path / "new").exists()  # the check leaves nothing behind


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_run_folder_is_one_line(tmp_path, capsys):
    from findview_baselines.cli import precheck

    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.raises(SystemExit) as exit_info:
            precheck("eval", "eval", [f"hydra.run.dir={ro / 'run'}"], check_run_dir=True)
    finally:
        ro.chmod(0o755)
    assert exit_info.value.code == 2 and "is not writable" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------
# Checkpoints: what the file is and what was expected
# ------------------------------------------------------------------------------------------------


def test_checkpoint_messages_say_what_the_file_is(tmp_path):
    from findview_baselines.rl.checkpoint import CheckpointError, CheckpointNotFound, load_checkpoint

    expected = "expected a .pth written by tools/train.py"
    text = tmp_path / "notes.pth"
    text.write_text("101 reasons\n")
    binary = tmp_path / "blob.pth"
    binary.write_bytes(bytes(range(256)) * 4)
    foreign = tmp_path / "foreign.pth"
    torch.save({"weights": torch.zeros(2)}, foreign)
    cases = {
        text: "not a findview checkpoint (a text file; " + expected,
        tmp_path: "a folder, not a checkpoint file (" + expected,
        binary: "not a findview checkpoint (a binary file of another format; " + expected,
        foreign: "not a findview checkpoint (a torch file without findview's 'signature' and 'policy' entries; " + expected,
    }
    for path, message in cases.items():
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(path, key="checkpoint")
        assert str(info.value) == f"checkpoint={path}: {message})" or str(info.value).startswith(f"checkpoint={path}: {message}")
        assert "\n" not in str(info.value) and "weights_only" not in str(info.value)
    with pytest.raises(CheckpointNotFound, match="checkpoint not found"):
        load_checkpoint(tmp_path / "missing.pth")


def test_eval_with_a_text_file_as_checkpoint_is_one_line():
    proc = run_tool("eval.py", "checkpoint=README.md", *SMALL)
    line = one_error_line(proc, "eval")
    assert line == ("eval: error: checkpoint=README.md: not a findview checkpoint "
                    "(a text file; expected a .pth written by tools/train.py)")


# ------------------------------------------------------------------------------------------------
# checkpoint= implies the learned agent; user errors are the project's own types
# ------------------------------------------------------------------------------------------------


def test_checkpoint_implies_the_learned_agent_before_validation(capsys):
    from findview_baselines.cli import precheck
    from findview_baselines.evaluation.evaluate import checkpoint_implies_agent

    argv = ["checkpoint=x.pth", "agent.revisit_penalty=0", "agent.revisit_row_stride=30"]
    assert checkpoint_implies_agent(argv) == [*argv, "agent=ppo"]
    assert checkpoint_implies_agent(["checkpoint=x.pth", "agent=sift"]) == ["checkpoint=x.pth", "agent=sift"]
    assert checkpoint_implies_agent(["checkpoint=null", "agent.d_thresh=3"]) == ["checkpoint=null", "agent.d_thresh=3"]
    precheck("eval", "eval", checkpoint_implies_agent(argv))  # no SystemExit: the keys are the learned agent's
    precheck("eval", "eval", checkpoint_implies_agent(["-m", "checkpoint=a.pth,b.pth", "agent.revisit_penalty=0,1"]))
    with pytest.raises(SystemExit):
        precheck("eval", "eval", argv)  # without the implied choice the default agent (orb) has no such key
    assert "agent.revisit_penalty" in capsys.readouterr().err


def test_override_parser_reads_keys_values_and_the_last_repeat():
    from findview_baselines.evaluation.evaluate import override_keys, override_values

    argv = ["-m", "+agent.x=1", "~corruption", "sim.fov=60", "checkpoint=a=b.pth", "sim.fov=90", "--cfg"]
    assert override_values(argv) == {"agent.x": "1", "sim.fov": "90", "checkpoint": "a=b.pth"}
    assert override_keys(argv) == {"agent.x", "sim.fov", "checkpoint"}


def test_user_errors_are_the_projects_own_types():
    from findview.config import ConfigError
    from findview.dataset import DatasetError, SamplingError
    from findview.dataset.splits import MissingDataFile
    from findview.imageio import PanoramaError
    from findview_baselines.cli import USER_ERRORS, UserError
    from findview_baselines.rl.checkpoint import CheckpointError, CheckpointNotFound, OutputPathError

    for bare in (ValueError, FileNotFoundError, PermissionError, OSError, KeyError, RuntimeError):
        assert bare not in USER_ERRORS
        assert not isinstance(bare("x"), USER_ERRORS)  # a bug inside the library keeps its traceback
    for cls in (UserError, ConfigError, DatasetError, MissingDataFile, PanoramaError, SamplingError, CheckpointError,
                CheckpointNotFound, OutputPathError):
        assert isinstance(cls("x"), USER_ERRORS)
    # callers that catch the builtin bases keep working
    assert issubclass(MissingDataFile, FileNotFoundError) and issubclass(CheckpointNotFound, FileNotFoundError)
    assert issubclass(CheckpointError, ValueError) and issubclass(OutputPathError, PermissionError)


def test_missing_and_broken_data_files_raise_data_errors(tmp_path):
    from findview.dataset import DatasetError, load_episodes, read_splits
    from findview.dataset.splits import MissingDataFile

    with pytest.raises(MissingDataFile, match="splits file not found"):
        read_splits(tmp_path)
    (tmp_path / "splits.json").write_text("{ not json")
    with pytest.raises(DatasetError, match="not valid JSON"):
        read_splits(tmp_path)
    bad = tmp_path / "test_fov90.json"
    bad.write_text('{"episodes": [{"episode_id": "x"}]}')
    with pytest.raises(DatasetError, match="not a findview episode record"):
        load_episodes(bad)
