"""The training run (findview_baselines.training.train, tools/train.py): exact resume, checkpoint
files, fine-tuning signature checks, NaN handling and early failure on an unwritable run folder.

Everything runs on CPU with a tiny setup: 48x48 views, 2 envs, 8-step rollouts, GRU 32, 300-step
episodes, a 10-panorama folder dataset (256x128 textured images) and 3 val episodes.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from _training import SIZE, digest, load, make_config
from findview_baselines.rl.checkpoint import CheckpointError
from findview_baselines.training import TrainingDiverged, select_val_episodes, train

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------------


def test_resume_gives_the_same_weights_as_one_run(make_cfg, reference_run: Path, tmp_path: Path) -> None:
    """3 updates, stop, re-run the same config -> identical weights / optimizer / env state after 6."""
    first = train(make_cfg(**{"trainer.stop_after": 3}), tmp_path)
    assert not first.completed and first.updates == 3
    assert load(tmp_path / "checkpoints" / "latest.pth")["update"] == 3
    second = train(make_cfg(), tmp_path)
    assert second.completed and second.updates == 6

    full = load(reference_run / "checkpoints" / "latest.pth")
    split = load(tmp_path / "checkpoints" / "latest.pth")
    assert full["update"] == split["update"] == 6
    for name, tensor in full["policy"].items():
        assert torch.equal(tensor, split["policy"][name]), name
    opt_full, opt_split = full["trainer"]["ppo"]["optimizer"]["state"], split["trainer"]["ppo"]["optimizer"]["state"]
    for key in opt_full:
        for field in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt_full[key][field], opt_split[key][field])
    assert full["trainer"]["env"]["episodes"] == split["trainer"]["env"]["episodes"]
    assert torch.equal(full["trainer"]["storage"]["hidden"], split["trainer"]["storage"]["hidden"])
    assert full["trainer"]["scheduler"]["current_level"] == split["trainer"]["scheduler"]["current_level"] == 3
    assert full["val"] == split["val"] and full["best_val_eps"] == split["best_val_eps"]

    # a finished run re-run is a no-op
    again = train(make_cfg(), tmp_path)
    assert again.completed and again.updates == 6 and load(tmp_path / "checkpoints" / "latest.pth")["env_steps"] == 96


def test_keep_val_checkpoints_writes_every_validation(make_cfg, reference_run: Path, tmp_path: Path) -> None:
    """trainer.keep_val_checkpoints: val_u<update>.pth at each validation (3 and 6), weights only; the run's
    weights are those of the run without the option, and best.pth is the one of the two with the lower val eps."""
    train(make_cfg(**{"trainer.keep_val_checkpoints": True}), tmp_path)
    ckpt_dir = tmp_path / "checkpoints"
    assert sorted(p.name for p in ckpt_dir.iterdir()) == ["best.pth", "latest.pth", "val_u00003.pth", "val_u00006.pth"]
    kept = {u: load(ckpt_dir / f"val_u{u:05d}.pth") for u in (3, 6)}
    assert [kept[u]["update"] for u in (3, 6)] == [3, 6] and all(k["trainer"] is None for k in kept.values())
    reference = load(reference_run / "checkpoints" / "latest.pth")
    for name, tensor in reference["policy"].items():
        assert torch.equal(tensor, kept[6]["policy"][name]), name
    lower = min((3, 6), key=lambda u: kept[u]["val"]["all"]["eps"])
    best = load(ckpt_dir / "best.pth")
    assert best["update"] == lower and all(torch.equal(t, kept[lower]["policy"][n]) for n, t in best["policy"].items())


@pytest.mark.parametrize("trainer", ["ppo", "dagger"])
def test_validation_does_not_change_the_trained_weights(make_cfg, reference_run: Path, tmp_path: Path, trainer: str) -> None:
    """The same run with validations at updates 3 and 6 and with none ends with the same weights, bit for bit: the
    val episodes draw from their own generators, so how often a run validates never changes what it learns (the
    presets whose file is the last update may switch their validations off to save time)."""
    def run(folder: Path, with_val: bool) -> dict:
        overrides: dict = {} if with_val else {"trainer.val_interval": 0, "trainer.val_at_end": False}
        if trainer == "dagger":
            overrides.update({  # as the robust presets: corrupted targets, search memory, rollout in a second thread
                "trainer": "dagger", "trainer.dagger.rollout_steps": 8, "trainer.dagger.seq_len": 8,
                "trainer.dagger.overlap_rollout": True, "corruption.name": "all", "corruption.severity": "[1,5]",
                "agent.revisit_penalty": 16.0,
            })
        train(make_cfg(**overrides), folder)
        return load(folder / "checkpoints" / "latest.pth")

    validated = load(reference_run / "checkpoints" / "latest.pth") if trainer == "ppo" else run(tmp_path / "val", True)
    plain = run(tmp_path / "plain", False)
    assert validated["val"] is not None and plain["val"] is None  # one run validated, the other did not
    assert validated["update"] == plain["update"] == 6
    for name, tensor in validated["policy"].items():
        assert torch.equal(tensor, plain["policy"][name]), name


def test_checkpoints_load_with_weights_only(reference_run: Path) -> None:
    ckpt_dir = reference_run / "checkpoints"
    assert sorted(p.name for p in ckpt_dir.iterdir()) == ["best.pth", "latest.pth"]  # no temp files left
    latest, best = load(ckpt_dir / "latest.pth"), load(ckpt_dir / "best.pth")
    for state in (latest, best):
        assert state["format"] == "findview-ppo"
        assert state["signature"] == {"variant": "early_fusion", "hidden_size": 32, "height": SIZE, "width": SIZE}
        assert isinstance(state["config"], dict) and state["config"]["sim"]["height"] == SIZE
        assert set(state["val"]) == {"easy", "medium", "hard", "all"}
    assert best["trainer"] is None and latest["trainer"] is not None
    assert best["best_val_eps"] == pytest.approx(min(best["val"]["all"]["eps"], latest["best_val_eps"]))
    assert {"torch", "numpy", "python"} <= set(latest["trainer"]["rng"])
    assert (reference_run / "resolved_config.yaml").is_file()
    assert any((reference_run / "tb").iterdir())


def test_init_from_loads_weights_and_checks_the_model(make_cfg, reference_run: Path, tmp_path: Path) -> None:
    ckpt = reference_run / "checkpoints" / "best.pth"
    with pytest.raises(CheckpointError, match=r"init_from=.*best.pth: checkpoint does not fit this model: height is 48 in the checkpoint but 40"):
        train(make_cfg(**{"init_from": str(ckpt), "sim.height": 40}), tmp_path / "other_size")
    with pytest.raises(CheckpointError, match=r"hidden_size is 32 in the checkpoint but 16"):
        train(make_cfg(**{"init_from": str(ckpt), "agent.hidden_size": 16}), tmp_path / "other_hidden")

    # same model: fine-tuning starts at update 0 with a fresh optimizer from the checkpoint's weights
    result = train(make_cfg(**{"init_from": str(ckpt), "trainer.num_updates": 1, "trainer.val_at_end": False}), tmp_path / "ft")
    state = load(result.latest)
    assert state["update"] == 1 and state["trainer"]["ppo"]["optimizer"]["state"][0]["step"].item() == 2  # 2 epochs
    start = load(ckpt)["policy"]
    moved = [name for name, t in state["policy"].items() if not torch.equal(t, start[name])]
    assert moved  # trained further from the loaded weights


def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(make_cfg, tmp_path: Path) -> None:
    train(make_cfg(**{"trainer.stop_after": 2}), tmp_path)
    latest = tmp_path / "checkpoints" / "latest.pth"
    before = (digest(latest), latest.stat().st_mtime_ns)
    with pytest.raises(TrainingDiverged, match=r"diverged at update 3: .*non-finite.*update 2\) was kept"):
        train(make_cfg(**{"trainer.ppo.entropy_coef": math.nan}), tmp_path)
    assert (digest(latest), latest.stat().st_mtime_ns) == before
    assert load(latest)["update"] == 2


def test_unwritable_run_folder_fails_before_training(tmp_path: Path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    # the dataset does not even exist: the write check must come first
    cfg = make_config(tmp_path / "missing_images", tmp_path / "missing_out")
    with pytest.raises(PermissionError, match=r"run folder .*a_file/run is not writable"):
        train(cfg, blocker / "run")
    assert not (tmp_path / "missing_out").exists()

    if os.geteuid() == 0:
        pytest.skip("running as root: a read-only folder does not block writes (the path-below-a-file case passed)")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(PermissionError, match=r"not writable"):
            train(cfg, locked / "run")
    finally:
        locked.chmod(0o700)


def test_val_episode_cap_spreads_over_difficulties() -> None:
    from findview.episode import Episode

    episodes = [
        Episode(f"{d}-{i}", "x.jpg", 0, 0, 0, 20, difficulty=d) for d in ("easy", "medium", "hard") for i in range(10)
    ]
    picked = select_val_episodes(episodes, 7)
    assert [e.difficulty for e in picked].count("easy") == 3 and len(picked) == 7
    assert {e.difficulty for e in picked} == {"easy", "medium", "hard"}
    assert [e.episode_id for e in picked[:3]] == ["easy-0", "easy-3", "easy-6"]
    assert select_val_episodes(episodes, None) == episodes


def test_cli_resumes_the_same_run_folder(panorama_folder: Path, dataset_out: Path, tmp_path: Path) -> None:
    """tools/train.py with Hydra overrides: the run folder holds .hydra/ and checkpoints; re-running resumes."""
    assert (REPO / "configs" / "dataset" / "folder.yaml").is_file(), "configs/dataset/folder.yaml is missing"
    run_dir = tmp_path / "cli_run"
    args = [
        sys.executable, str(REPO / "tools" / "train.py"), "agent=ppo", "dataset=folder",
        f"dataset.root={panorama_folder}", f"dataset.out_dir={dataset_out}", "dataset.name=testfolder",
        f"sim.height={SIZE}", f"sim.width={SIZE}", "sim.device=cpu", "task.max_steps=300",
        "agent.hidden_size=32", "trainer.ppo.rollout_steps=8", "trainer.num_envs=2", "trainer.num_updates=2",
        "trainer.val_interval=0", "trainer.val_episodes=3", "trainer.progress=false", "trainer.torch_threads=1",
        f"hydra.run.dir={run_dir}",
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    done = subprocess.run(args + ["trainer.stop_after=1"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (run_dir / ".hydra" / "config.yaml").is_file() and load(run_dir / "checkpoints" / "latest.pth")["update"] == 1
    done = subprocess.run(args, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "resumed" in done.stdout + done.stderr
    assert load(run_dir / "checkpoints" / "latest.pth")["update"] == 2

    blocked = tmp_path / "a_file"
    blocked.write_text("")
    done = subprocess.run(args[:-1] + [f"hydra.run.dir={blocked}/run"], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode != 0 and "not writable" in done.stderr
