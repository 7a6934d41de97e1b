"""Runs that fail safely: SIGTERM / SIGINT during training, one live run per folder, and the validation
inside training being the same code path as ``tools/eval.py checkpoint=...``.

Reuses the tiny setup of test_train.py (48x48 views, 2 envs, 8-step rollouts, a 10-panorama folder).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from findview_baselines.cli import Interrupted, UserError
from findview_baselines.training import train
from findview_baselines.rl.safety import RunLock, lock_holder
from _training import SIZE, load

REPO = Path(__file__).resolve().parents[1]


def tb_steps(run_dir: Path, tag: str) -> list[int]:
    """Every step written for ``tag`` in all event files of ``run_dir/tb`` (duplicates kept)."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    steps: list[int] = []
    for path in sorted((run_dir / "tb").glob("events.out.tfevents.*")):
        for event in EventFileLoader(str(path)).Load():
            if event.HasField("summary") and any(v.tag == tag for v in event.summary.value):
                steps.append(int(event.step))
    return steps


def _tool_args(panorama_folder: Path, dataset_out: Path, run_dir: Path, *extra: str) -> list[str]:
    return [
        sys.executable, str(REPO / "tools" / "train.py"), "dataset=folder",
        f"dataset.root={panorama_folder}", f"dataset.out_dir={dataset_out}", "dataset.name=testfolder",
        f"sim.height={SIZE}", f"sim.width={SIZE}", "sim.device=cpu", "sim.prefetch_workers=0", "task.max_steps=300",
        "agent.hidden_size=32", "trainer.ppo.rollout_steps=8", "trainer.ppo.ppo_epochs=2", "trainer.num_envs=2",
        "trainer.val_interval=0", "trainer.val_at_end=false", "trainer.log_interval=1",
        "trainer.checkpoint_interval=1", "trainer.progress=false", "trainer.torch_threads=1",
        f"hydra.run.dir={run_dir}", *extra,
    ]


def test_sigterm_saves_refuses_a_second_run_and_resumes_without_gaps(panorama_folder, dataset_out, tmp_path) -> None:
    """A real training process: a second run into its folder is refused naming the pid; SIGTERM makes it
    write latest.pth and exit 143 with a resume hint; re-running continues from the saved update, and
    TensorBoard holds every update exactly once."""
    run_dir = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    args = _tool_args(panorama_folder, dataset_out, run_dir, "trainer.num_updates=100000")
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        deadline = time.time() + 240
        latest = run_dir / "checkpoints" / "latest.pth"
        while not latest.is_file() and time.time() < deadline and proc.poll() is None:
            time.sleep(0.5)
        assert latest.is_file(), proc.stderr.read() if proc.poll() is not None else "no checkpoint in time"
        assert lock_holder(run_dir) == proc.pid

        second = subprocess.run(args, capture_output=True, text=True, env=env, timeout=120)
        assert second.returncode == 2
        line = second.stderr.strip().splitlines()[-1]
        assert str(run_dir) in line and f"pid {proc.pid}" in line

        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143, err[-2000:]
    saved = load(run_dir / "checkpoints" / "latest.pth")["update"]
    last = err.strip().splitlines()[-1]
    assert f"stopped at update {saved}" in last and "latest.pth" in last and "resume" in last
    assert lock_holder(run_dir) is None
    per_update = 2 * 8  # TensorBoard's x-axis is env steps: 2 envs x 8 rollout steps per update
    assert tb_steps(run_dir, "loss/policy_loss") == [per_update * k for k in range(1, saved + 1)]

    done = subprocess.run(
        _tool_args(panorama_folder, dataset_out, run_dir, "trainer.num_updates=100000", "trainer.stop_after=2"),
        capture_output=True, text=True, env=env, timeout=240,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"resumed {run_dir} at update {saved}" in done.stdout + done.stderr
    assert load(run_dir / "checkpoints" / "latest.pth")["update"] == saved + 2
    steps = tb_steps(run_dir, "loss/policy_loss")
    assert sorted(steps) == [per_update * k for k in range(1, saved + 3)] and len(set(steps)) == len(steps)


def test_signal_during_a_rollout_abandons_the_update_and_resumes_exactly(
    make_cfg, reference_run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGINT in the middle of update 4's rollout: latest.pth describes the state after update 3, and
    resuming to 6 updates gives exactly the weights of the uninterrupted run."""
    from findview.task.env import FindViewEnv

    original = FindViewEnv.step
    calls = {"n": 0}
    per_update = 8  # rollout steps

    def step(self, actions):
        if self.num_envs == 2 and not isinstance(self.source, type(None)) and hasattr(self.source, "sampler"):
            calls["n"] += 1
            if calls["n"] == 3 * per_update + 5:  # inside update 4's rollout
                os.kill(os.getpid(), signal.SIGINT)
        return original(self, actions)

    monkeypatch.setattr(FindViewEnv, "step", step)
    with pytest.raises(Interrupted) as info:
        train(make_cfg(), tmp_path)
    assert info.value.signum == signal.SIGINT and "stopped at update 3" in str(info.value)
    assert load(tmp_path / "checkpoints" / "latest.pth")["update"] == 3
    monkeypatch.setattr(FindViewEnv, "step", original)

    result = train(make_cfg(), tmp_path)
    assert result.completed and result.updates == 6
    full = load(reference_run / "checkpoints" / "latest.pth")
    split = load(tmp_path / "checkpoints" / "latest.pth")
    for name, tensor in full["policy"].items():
        assert torch.equal(tensor, split["policy"][name]), name
    assert full["trainer"]["env"]["episodes"] == split["trainer"]["env"]["episodes"]


def test_a_stale_lock_is_taken_over_and_a_live_one_refused(tmp_path: Path) -> None:
    (tmp_path / ".run.lock").write_text("999999\n")  # a killed run's file: no process holds the flock
    assert lock_holder(tmp_path) is None
    with RunLock(tmp_path):
        assert lock_holder(tmp_path) == os.getpid()
        code = (
            "import sys; from findview_baselines.rl.safety import RunLock\n"
            f"RunLock({str(tmp_path)!r}).__enter__()"
        )
        other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert other.returncode != 0 and f"pid {os.getpid()}" in other.stderr and str(tmp_path) in other.stderr
    assert lock_holder(tmp_path) is None


def test_training_into_a_locked_folder_is_a_user_error(make_cfg, tmp_path: Path) -> None:
    with RunLock(tmp_path):
        with pytest.raises(UserError, match=rf"run folder {tmp_path} is in use .*pid {os.getpid()}"):
            train(make_cfg(), tmp_path)


def test_val_eps_in_the_checkpoint_equals_tools_eval(reference_run: Path, panorama_folder, dataset_out, tmp_path) -> None:
    """best.pth's stored validation equals what tools/eval.py split=val checkpoint=... reports for it; the
    view size comes from the checkpoint and the output folder is named after the checkpoint's run."""
    best = reference_run / "checkpoints" / "best.pth"
    stored = load(best)["val"]
    outputs = tmp_path / "cwd"
    outputs.mkdir()
    args = [
        sys.executable, str(REPO / "tools" / "eval.py"), "split=val", f"checkpoint={best}", "dataset=folder",
        f"dataset.root={panorama_folder}", f"dataset.out_dir={dataset_out}", "dataset.name=testfolder",
        "sim.device=cpu", "task.max_steps=300", "num_envs=2", "progress=false",
    ]
    done = subprocess.run(args, capture_output=True, text=True, cwd=outputs, timeout=240,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert done.returncode == 0, done.stderr[-3000:]
    (run,) = (outputs / "outputs" / "eval").iterdir()
    assert run.name == f"{reference_run.name}-best_folder_val"  # <checkpoint run>-<file>_<dataset choice>_<split>
    (stamp,) = run.iterdir()
    summary = json.loads((stamp / "summary.json").read_text())
    for difficulty in ("easy", "medium", "hard"):
        assert summary[difficulty]["eps"] == pytest.approx(stored[difficulty]["eps"], abs=1e-9), difficulty
        assert summary[difficulty]["spl"] == pytest.approx(stored[difficulty]["spl"], abs=1e-9), difficulty
    config = (stamp / ".hydra" / "config.yaml").read_text()
    assert "name: ppo" in config and f"height: {SIZE}" in config and "name: orb" not in config


def test_user_errors_are_one_line_exit_2_and_leave_no_empty_run_folder(make_cfg, tmp_path: Path) -> None:
    """A file that is not a checkpoint (eval) and an unreadable resume state (train): one line naming the
    file and the way out, exit 2, and no output folder left behind by the failed eval."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    bogus = tmp_path / "not_a_checkpoint.pth"
    bogus.write_text("hello")
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    done = subprocess.run(
        [sys.executable, str(REPO / "tools" / "eval.py"), f"checkpoint={bogus}", "progress=false"],
        capture_output=True, text=True, cwd=cwd, env=env, timeout=180,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert lines[-1].startswith("eval: error: ") and str(bogus) in lines[-1] and "checkpoint" in lines[-1]
    assert not (cwd / "outputs").exists() or not any((cwd / "outputs").rglob("*.json"))
    assert not any(p.is_dir() and p.name.startswith("not_a_checkpoint") for p in (cwd / "outputs").rglob("*")) \
        if (cwd / "outputs").exists() else True

    run_dir = tmp_path / "run"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "latest.pth").write_bytes(b"\0garbage")
    with pytest.raises(UserError, match=r"latest.pth.*trainer.resume=false"):
        train(make_cfg(), run_dir)


def test_a_training_that_fails_on_its_input_leaves_no_run_folder(tmp_path: Path) -> None:
    run_dir = tmp_path / "outputs" / "run"
    done = subprocess.run(
        [sys.executable, str(REPO / "tools" / "train.py"), "dataset=folder", f"dataset.root={tmp_path / 'nowhere'}",
         f"dataset.out_dir={tmp_path / 'data'}", f"hydra.run.dir={run_dir}", "trainer.progress=false"],
        capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=180,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip().splitlines()[-1].startswith("train: error: ") and "nowhere" in done.stderr
    assert not run_dir.exists()


def test_sigint_skips_a_scheduled_validation_and_writes_latest(make_cfg, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGINT while update 3 (a validation update: val_interval 3) trains: the update is finished, the
    validation is skipped (no best.pth, no val scalars), latest.pth holds update 3 and the run stops."""
    from findview_baselines.rl import ppo_trainer
    from findview_baselines.training.callbacks import ValidationCallback

    original = ppo_trainer.PPOTrainer.train_update

    def train_update(self, *args, **kwargs):
        stats = original(self, *args, **kwargs)
        if self.update == 3:
            os.kill(os.getpid(), signal.SIGINT)  # after the rollout: the update completes
        return stats

    validated: list[int] = []
    monkeypatch.setattr(ppo_trainer.PPOTrainer, "train_update", train_update)
    monkeypatch.setattr(ValidationCallback, "validate", lambda self, ctx: validated.append(ctx.algo.update) or {})
    with pytest.raises(Interrupted) as info:
        train(make_cfg(), tmp_path)
    assert info.value.signum == signal.SIGINT and "stopped at update 3" in str(info.value)
    assert validated == []
    assert load(tmp_path / "checkpoints" / "latest.pth")["update"] == 3
    assert not (tmp_path / "checkpoints" / "best.pth").exists()
