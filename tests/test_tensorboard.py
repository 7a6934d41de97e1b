"""TensorBoard gets every metric a trainer reports, under a stable tag, against env steps: one DAgger
update, then one PPO update fine-tuning it (KL anchor, critic warm-up and auxiliary head on, so that every
optional stat is reported), each checked against its own event file."""

from __future__ import annotations

from pathlib import Path

import pytest

from findview_baselines.rl import dagger, ppo_trainer
from findview_baselines.training import tb_tag, train


def _scalars(run_dir: Path) -> dict[str, list[int]]:
    """``{tag: [steps]}`` of every scalar in the run's event files."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: [e.step for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def _record_stats(monkeypatch: pytest.MonkeyPatch, cls: type) -> list[dict]:
    seen: list[dict] = []
    original = cls.train_update

    def train_update(self, *args, **kwargs):
        stats = original(self, *args, **kwargs)
        seen.append({**stats, "_env_steps": self.env_steps})
        return stats

    monkeypatch.setattr(cls, "train_update", train_update)
    return seen


def _check_every_key_logged(seen: list[dict], run_dir: Path) -> dict[str, list[int]]:
    scalars = _scalars(run_dir)
    assert len(seen) == 1
    stats = seen[0]
    numeric = {k for k, v in stats.items() if isinstance(v, (int, float)) and not k.startswith("_")}
    missing = {k: tb_tag(k) for k in numeric if tb_tag(k) is not None and tb_tag(k) not in scalars}
    assert not missing, f"reported but not in TensorBoard: {missing}"
    # the x-axis is env steps; the update index is a scalar of its own
    env_steps = stats["_env_steps"]
    assert env_steps > 1
    assert all(steps == [env_steps] for steps in scalars.values()), scalars
    return scalars


def test_every_reported_metric_reaches_tensorboard(make_cfg, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    quiet = {"trainer.num_updates": 1, "trainer.val_interval": 0, "trainer.val_at_end": False}
    seen = _record_stats(monkeypatch, dagger.DAggerTrainer)
    imitate = tmp_path / "imitate"
    train(make_cfg(**quiet, **{"trainer": "dagger", "trainer.dagger.rollout_steps": 8, "trainer.dagger.seq_len": 8,
                               "trainer.dagger.batch_sequences": 2}), imitate)
    scalars = _check_every_key_logged(seen, imitate)
    for key in ("beta", "oracle_share", "rollout_agreement", "policy_loss"):
        assert key in seen[0], f"DAgger no longer reports {key}"
    assert "schedule/beta" in scalars and "update/oracle_share" in scalars and "progress/update" in scalars
    assert not any(tag.startswith("loss/beta") for tag in scalars)  # beta is a schedule, not a loss

    seen = _record_stats(monkeypatch, ppo_trainer.PPOTrainer)
    finetune = tmp_path / "finetune"
    train(make_cfg(**quiet, **{"init_from": str(imitate / "checkpoints" / "latest.pth"), "trainer.ppo.kl_to_init_coef": 0.1,
                               "trainer.ppo.critic_warmup_updates": 1, "trainer.ppo.aux_coef": 0.1}), finetune)
    scalars = _check_every_key_logged(seen, finetune)
    for key in ("kl_to_init", "critic_warmup", "aux_loss", "approx_kl", "entropy"):
        assert key in seen[0], f"PPO no longer reports {key}"
    assert "update/kl_to_init" in scalars and "schedule/critic_warmup" in scalars and "loss/aux_loss" in scalars
