"""The trainer base class (findview_baselines.rl.trainer_base): the interface both trainers share."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from findview_baselines.rl.dagger import DAggerConfig, DAggerTrainer
from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo import PPOConfig
from findview_baselines.rl.ppo_trainer import PPOTrainer
from findview_baselines.rl.ppo_trainer import UpdateAbandoned as ReexportedUpdateAbandoned
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.trainer_base import TIMING_KEYS, Trainer, UpdateAbandoned

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SIZE = 32  # 32x32 views (the correlation encoder's smallest)
NUM_ENVS = 3
ROLLOUT = 4


class TinyEnv:
    """FindViewEnv-shaped toy with the privileged state the oracle labels read: episodes of ``length`` steps,
    reward 1 for RIGHT (3); the view shows the step count, the target is constant grey; the target sits
    10 degrees right of the start (so the oracle's label is RIGHT, then STOP)."""

    def __init__(self, num_envs: int = NUM_ENVS, length: int = 3) -> None:
        self.num_envs, self.length = num_envs, length
        self.steps = torch.zeros(num_envs, dtype=torch.long)
        self.new_episode = torch.ones(num_envs, dtype=torch.bool)
        self.active = torch.ones(num_envs, dtype=torch.bool)
        self.pitch = torch.zeros(num_envs, dtype=torch.long)
        self.yaw = torch.zeros(num_envs, dtype=torch.long)
        self.target_pitch = torch.zeros(num_envs, dtype=torch.long)
        self.target_yaw = torch.full((num_envs,), 10, dtype=torch.long)
        self.step_deg = 1
        self.sim = SimpleNamespace(fov=90.0)

    def _obs(self) -> dict[str, torch.Tensor]:
        view = (self.steps * 40).to(torch.uint8).view(-1, 1, 1, 1).expand(-1, 3, SIZE, SIZE).clone()
        return {"view": view, "target": torch.full_like(view, 128)}

    def reset(self) -> dict[str, torch.Tensor]:
        self.steps.zero_()
        self.new_episode.fill_(True)
        return self._obs()

    def step(self, actions: torch.Tensor):
        reward = (actions.cpu() == 3).float()
        self.steps += 1
        done = self.steps >= self.length
        infos = [{"steps": int(self.steps[i])} if done[i] else None for i in range(self.num_envs)]
        self.steps[done] = 0
        self.new_episode = done.clone()
        return self._obs(), reward, done, infos


def make_trainer(kind: str, aux: bool = False) -> Trainer:
    """A fresh trainer of ``kind`` (``"ppo"`` | ``"dagger"``) on a :class:`TinyEnv`, started."""
    torch.manual_seed(0)
    env = TinyEnv()
    policy = Policy(SIZE, SIZE, variant="correlation", hidden_size=8)
    aux_coef = 0.5 if aux else 0.0
    trainer: Trainer
    if kind == "ppo":
        cfg = PPOConfig(rollout_steps=ROLLOUT, ppo_epochs=1, num_mini_batches=1, aux_coef=aux_coef)
        trainer = PPOTrainer(env, policy, cfg, total_updates=4, scheduler=DifficultyScheduler(4))
    else:
        dcfg = DAggerConfig(rollout_steps=ROLLOUT, seq_len=2, buffer_size=64, batch_sequences=2, aux_coef=aux_coef)
        trainer = DAggerTrainer(env, policy, dcfg, total_updates=4, scheduler=DifficultyScheduler(4))
    trainer.start()
    return trainer


def test_both_trainers_are_trainers_of_their_kind() -> None:
    assert issubclass(PPOTrainer, Trainer) and issubclass(DAggerTrainer, Trainer)
    assert (PPOTrainer.kind, DAggerTrainer.kind) == ("ppo", "dagger")
    assert PPOTrainer.supports_preemption and not DAggerTrainer.supports_preemption
    assert ReexportedUpdateAbandoned is UpdateAbandoned  # old imports from ppo_trainer still catch it
    with pytest.raises(TypeError):
        Trainer(TinyEnv(), Policy(SIZE, SIZE, variant="correlation", hidden_size=8), None, 1)  # type: ignore[abstract]


@pytest.mark.parametrize("kind", ["ppo", "dagger"])
def test_state_records_its_kind(kind: str) -> None:
    trainer = make_trainer(kind)
    state = trainer.state_dict()
    assert state["kind"] == kind
    make_trainer(kind).load_state_dict(state)  # its own kind loads


def test_a_state_of_one_kind_is_refused_by_the_other() -> None:
    ppo, dagger = make_trainer("ppo"), make_trainer("dagger")
    with pytest.raises(ValueError, match=r"not saved by the DAgger trainer \(trainer=dagger\) but by the 'ppo' one"):
        dagger.load_state_dict(ppo.state_dict())
    with pytest.raises(ValueError, match=r"not saved by the PPO trainer \(trainer=ppo\) but by the 'dagger' one"):
        ppo.load_state_dict(dagger.state_dict())


def test_a_ppo_state_without_kind_still_resumes() -> None:
    """PPO states saved before ``kind`` existed have none: they are PPO states, DAgger refuses them."""
    trainer = make_trainer("ppo")
    trainer.train_update()
    old = {k: v for k, v in trainer.state_dict().items() if k != "kind"}
    resumed = make_trainer("ppo")
    resumed.load_state_dict(old)
    assert resumed.update == 1 and resumed.env_steps == trainer.env_steps
    with pytest.raises(ValueError, match="not saved by the DAgger trainer"):
        make_trainer("dagger").load_state_dict(old)


@pytest.mark.parametrize("kind", ["ppo", "dagger"])
def test_pop_timings_and_steps_per_update(kind: str) -> None:
    trainer = make_trainer(kind)
    assert trainer.steps_per_update == ROLLOUT * NUM_ENVS
    stats = trainer.train_update()
    assert stats["update"] == 1 and stats["env_steps"] == trainer.steps_per_update == trainer.env_steps
    timings = trainer.pop_timings()
    assert tuple(timings) == TIMING_KEYS
    assert all(v >= 0 for v in timings.values()) and timings["update"] > 0 and timings["env_step"] > 0
    assert trainer.pop_timings() == dict.fromkeys(TIMING_KEYS, 0.0)  # reset by the call


@pytest.mark.parametrize("kind", ["ppo", "dagger"])
def test_extra_modules_are_the_aux_heads(kind: str) -> None:
    assert make_trainer(kind, aux=False).extra_modules() == []
    trainer = make_trainer(kind, aux=True)
    head = trainer.ppo.aux_head if isinstance(trainer, PPOTrainer) else trainer.aux_head
    assert head is not None and trainer.extra_modules() == [head]


def test_episode_returns_are_summed_per_slot_and_reset_at_done() -> None:
    trainer = make_trainer("ppo")
    none = [None] * NUM_ENVS
    assert trainer._track_returns(torch.tensor([1.0, 2.0, 0.5]), torch.zeros(NUM_ENVS, dtype=torch.bool), none) == []
    done = torch.tensor([False, True, False])
    records = trainer._track_returns(torch.tensor([1.0, -1.0, 0.5]), done, [None, {"steps": 2}, None])
    assert records == [{"steps": 2, "return": 1.0}]
    assert trainer.episode_returns.tolist() == [2.0, 0.0, 1.0]


def test_state_during_an_abandoned_rollout_is_the_one_before_the_update() -> None:
    for kind in ("ppo", "dagger"):
        trainer = make_trainer(kind)
        before = trainer.state_dict()
        calls = iter(range(100))
        with pytest.raises(UpdateAbandoned, match="update 1 abandoned"):
            trainer.train_update(should_stop=lambda: next(calls) >= 2)
        after = trainer.state_dict()
        assert after["env_steps"] == before["env_steps"] == 0 and after["update"] == 0
        assert torch.equal(after["episode_returns"], before["episode_returns"])
