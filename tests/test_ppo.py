"""Rollout storage + GAE, PPO loss terms and update, linear decay, difficulty scheduler."""

from __future__ import annotations

import math

import pytest
import torch

from findview_baselines.rl.policy import Policy
from findview_baselines.rl.ppo import PPO, PPOConfig, linear_decay, ppo_loss
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import RolloutStorage

SIZE = 64  # images in these tests: 64x64 (smallest size the encoder is meant for)


def make_storage(T: int, N: int, hidden: int = 8) -> RolloutStorage:
    return RolloutStorage(T, N, SIZE, SIZE, hidden, device="cpu")


def blank_obs(N: int) -> dict[str, torch.Tensor]:
    zeros = torch.zeros(N, 3, SIZE, SIZE, dtype=torch.uint8)
    return {"view": zeros, "target": zeros.clone()}


# --------------------------------------------------------------------------------------------------
# GAE
# --------------------------------------------------------------------------------------------------


def test_gae_with_episode_end_in_the_middle() -> None:
    """T=3, N=2, gamma=0.9, lambda=0.5. Env 0's episode ends at step 1 (masks[2] = 0); env 1 runs on.

    env 0: rewards (1, 2, 3), values (0.5, 1.0, 2.0), next value 4.0
      t=2: delta = 3 + 0.9*4.0 - 2.0           = 4.6    A2 = 4.6
      t=1: delta = 2 + 0 (no bootstrap) - 1.0  = 1.0    A1 = 1.0 (no A2 either)
      t=0: delta = 1 + 0.9*1.0 - 0.5           = 1.4    A0 = 1.4 + 0.9*0.5*1.0 = 1.85
      returns = A + V = (2.35, 2.0, 6.6)
    env 1: rewards (0, 0, 1), values 0, next value 10.0
      t=2: delta = 1 + 0.9*10 = 10   A2 = 10
      t=1: delta = 0                 A1 = 0.45*10  = 4.5
      t=0: delta = 0                 A0 = 0.45*4.5 = 2.025
    """
    storage = make_storage(3, 2)
    storage.rewards.copy_(torch.tensor([[1.0, 0.0], [2.0, 0.0], [3.0, 1.0]]))
    storage.values[:3].copy_(torch.tensor([[0.5, 0.0], [1.0, 0.0], [2.0, 0.0]]))
    storage.masks.copy_(torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 1.0]]))
    advantages = storage.compute_returns(torch.tensor([4.0, 10.0]), gamma=0.9, lam=0.5)

    expected_adv = torch.tensor([[1.85, 2.025], [1.0, 4.5], [4.6, 10.0]])
    expected_ret = torch.tensor([[2.35, 2.025], [2.0, 4.5], [6.6, 10.0]])
    torch.testing.assert_close(advantages, expected_adv)
    torch.testing.assert_close(storage.returns, expected_ret)
    torch.testing.assert_close(storage.values[3], torch.tensor([4.0, 10.0]))


def test_gae_lambda_one_is_discounted_return_minus_value() -> None:
    """With lambda=1 and no episode end, A_t = sum_k gamma^k r_{t+k} + gamma^(T-t) V_T - V_t."""
    storage = make_storage(3, 1)
    storage.rewards.copy_(torch.tensor([[1.0], [1.0], [1.0]]))
    storage.values[:3].copy_(torch.tensor([[0.2], [0.3], [0.4]]))
    storage.masks.fill_(1.0)
    adv = storage.compute_returns(torch.tensor([2.0]), gamma=0.5, lam=1.0)
    # t=0: 1 + 0.5 + 0.25 + 0.125*2 - 0.2 = 1.8 ; t=1: 1 + 0.5 + 0.25*2 - 0.3 = 1.7 ; t=2: 1 + 1 - 0.4 = 1.6
    torch.testing.assert_close(adv.flatten(), torch.tensor([1.8, 1.7, 1.6]))


# --------------------------------------------------------------------------------------------------
# Storage
# --------------------------------------------------------------------------------------------------


def test_insert_after_update_and_overflow() -> None:
    T, N = 2, 3
    storage = make_storage(T, N)
    storage.set_initial(blank_obs(N))
    for t in range(T):
        obs = {k: torch.full_like(v, t + 1) for k, v in blank_obs(N).items()}
        storage.insert(
            obs,
            torch.full((N, 8), float(t + 1)),
            torch.full((N,), t, dtype=torch.long),
            torch.zeros(N),
            torch.zeros(N),
            torch.ones(N),
            torch.tensor([1.0, 0.0, 1.0]),
        )
    with pytest.raises(IndexError, match="full"):
        storage.insert(blank_obs(N), torch.zeros(N, 8), torch.zeros(N, dtype=torch.long), torch.zeros(N),
                       torch.zeros(N), torch.zeros(N), torch.ones(N))
    storage.after_update()
    assert storage.step == 0
    assert (storage.view[0] == T).all() and (storage.target[0] == T).all()
    assert (storage.hidden[0] == T).all()
    torch.testing.assert_close(storage.masks[0], torch.tensor([1.0, 0.0, 1.0]))
    obs, hidden, masks = storage.current()
    assert obs["view"].shape == (N, 3, SIZE, SIZE) and hidden.shape == (N, 8) and masks.shape == (N,)


@pytest.mark.parametrize("num_mini_batches", [1, 2, 3, 6])
def test_recurrent_minibatches_cover_each_env_once(num_mini_batches: int) -> None:
    T, N = 4, 6
    storage = make_storage(T, N)
    # tag every entry with its env id so we can check which column each mini-batch holds
    env_tag = torch.arange(N).float()
    storage.actions.copy_(torch.arange(N).expand(T, N))
    storage.hidden[0].copy_(env_tag[:, None].expand(N, 8))
    storage.view.copy_(torch.arange(N, dtype=torch.uint8).view(1, N, 1, 1, 1).expand_as(storage.view))
    storage.returns.copy_(torch.arange(T).float()[:, None] * 10 + env_tag)  # 10*t + env
    advantages = -storage.returns

    seen = []
    for batch in storage.recurrent_minibatches(advantages, num_mini_batches, torch.Generator().manual_seed(0)):
        n = len(batch.env_ids)
        seen += batch.env_ids.tolist()
        assert batch.view.shape == (T * n, 3, SIZE, SIZE) and batch.hidden0.shape == (n, 8)
        # time-major: row t * n + j is env env_ids[j] at step t
        expected = (torch.arange(T)[:, None] * 10 + batch.env_ids[None, :]).flatten().float()
        torch.testing.assert_close(batch.returns, expected)
        torch.testing.assert_close(batch.advantages, -expected)
        assert torch.equal(batch.actions, batch.env_ids.repeat(T))
        assert torch.equal(batch.view[:, 0, 0, 0].long(), batch.env_ids.repeat(T))
        torch.testing.assert_close(batch.hidden0[:, 0], batch.env_ids.float())
        assert batch.masks.shape == batch.old_log_probs.shape == batch.old_values.shape == (T * n,)
    assert sorted(seen) == list(range(N))

    with pytest.raises(ValueError, match="num_mini_batches"):
        next(storage.recurrent_minibatches(advantages, N + 1))


# --------------------------------------------------------------------------------------------------
# PPO loss terms (hand-computed)
# --------------------------------------------------------------------------------------------------


def test_ratio_clipping_positive_advantage_is_clipped_and_has_no_gradient() -> None:
    """ratio = 0.6 / 0.4 = 1.5, A = 2: min(1.5*2, 1.2*2) = 2.4 -> policy_loss = -2.4, no gradient."""
    new_lp = torch.tensor([math.log(0.6)], requires_grad=True)
    old_lp = torch.tensor([math.log(0.4)])
    zero = torch.zeros(1)
    terms = ppo_loss(new_lp, old_lp, torch.tensor([2.0]), zero, zero, zero, zero,
                     clip=0.2, value_coef=0.5, entropy_coef=0.01)
    torch.testing.assert_close(terms["policy_loss"], torch.tensor(-2.4))
    torch.testing.assert_close(terms["clip_fraction"], torch.tensor(1.0))
    torch.testing.assert_close(terms["approx_kl"], torch.tensor(0.5 - math.log(1.5)))  # (r-1) - log r
    terms["loss"].backward()
    assert new_lp.grad is not None and new_lp.grad.abs().item() == 0.0


def test_ratio_clipping_negative_advantage_keeps_unclipped_term() -> None:
    """ratio 1.5, A = -2: min(-3, -2.4) = -3 -> policy_loss = 3, gradient d/dlp (-ratio*A) = -1.5*(-2) = 3."""
    new_lp = torch.tensor([math.log(0.6)], requires_grad=True)
    old_lp = torch.tensor([math.log(0.4)])
    zero = torch.zeros(1)
    terms = ppo_loss(new_lp, old_lp, torch.tensor([-2.0]), zero, zero, zero, zero,
                     clip=0.2, value_coef=0.5, entropy_coef=0.0)
    torch.testing.assert_close(terms["policy_loss"], torch.tensor(3.0))
    terms["loss"].backward()
    torch.testing.assert_close(new_lp.grad, torch.tensor([3.0]))


def test_ratio_below_one_minus_clip() -> None:
    """ratio 0.5, A = 1: min(0.5, 0.8) = 0.5 (pessimistic term) -> -0.5; ratio 0.5, A = -1: min(-0.5, -0.8) = -0.8."""
    lp = torch.log(torch.tensor([0.5, 0.5]))
    zero = torch.zeros(2)
    terms = ppo_loss(lp, zero, torch.tensor([1.0, -1.0]), zero, zero, zero, zero,
                     clip=0.2, value_coef=0.5, entropy_coef=0.0)
    torch.testing.assert_close(terms["policy_loss"], torch.tensor(-(0.5 - 0.8) / 2))


def test_clipped_value_loss_and_total() -> None:
    """old_v = 1, v = 2, clip 0.2 -> v_clipped = 1.2.
    R = 3: (2-3)^2 = 1,  (1.2-3)^2 = 3.24 -> max 3.24
    R = 0: (2-0)^2 = 4,  (1.2-0)^2 = 1.44 -> max 4
    value_loss = 0.5 * mean(3.24, 4) = 1.81 ; unclipped: 0.5 * mean(1, 4) = 1.25
    loss = policy (0, ratio 1 and A 0) + 0.5 * 1.81 - 0.1 * mean entropy (1.0, 2.0) = 0.905 - 0.15 = 0.755
    """
    zero = torch.zeros(2)
    values = torch.tensor([2.0, 2.0])
    old_values = torch.tensor([1.0, 1.0])
    returns = torch.tensor([3.0, 0.0])
    entropy = torch.tensor([1.0, 2.0])
    terms = ppo_loss(zero, zero, zero, values, old_values, returns, entropy,
                     clip=0.2, value_coef=0.5, entropy_coef=0.1)
    torch.testing.assert_close(terms["value_loss"], torch.tensor(1.81))
    torch.testing.assert_close(terms["entropy"], torch.tensor(1.5))
    torch.testing.assert_close(terms["loss"], torch.tensor(0.755))
    plain = ppo_loss(zero, zero, zero, values, old_values, returns, entropy,
                     clip=0.2, value_coef=0.5, entropy_coef=0.1, clipped_value_loss=False)
    torch.testing.assert_close(plain["value_loss"], torch.tensor(1.25))


# --------------------------------------------------------------------------------------------------
# PPO update
# --------------------------------------------------------------------------------------------------


def filled_storage(policy: Policy, T: int, N: int, action: int, reward: float, seed: int = 0) -> RolloutStorage:
    """A rollout of random images where every step took ``action`` and got ``reward`` (no episode ends)."""
    g = torch.Generator().manual_seed(seed)
    storage = RolloutStorage(T, N, SIZE, SIZE, policy.hidden_size)
    storage.view.copy_(torch.randint(0, 256, storage.view.shape, dtype=torch.uint8, generator=g))
    storage.target.copy_(torch.randint(0, 256, storage.target.shape, dtype=torch.uint8, generator=g))
    storage.masks.fill_(1.0)
    storage.masks[0] = 0.0
    storage.actions.fill_(action)
    storage.rewards.fill_(reward)
    with torch.no_grad():
        lp, v, _ = policy.evaluate_actions(
            {"view": storage.view[:T].flatten(0, 1), "target": storage.target[:T].flatten(0, 1)},
            storage.hidden[0], storage.masks[:T].flatten(), storage.actions.flatten(),
        )
        storage.log_probs.copy_(lp.view(T, N))
        storage.values[:T].copy_(v.view(T, N))
    storage.step = T
    return storage


def mean_log_prob(policy: Policy, storage: RolloutStorage) -> float:
    T = storage.num_steps
    with torch.no_grad():
        lp, _, _ = policy.evaluate_actions(
            {"view": storage.view[:T].flatten(0, 1), "target": storage.target[:T].flatten(0, 1)},
            storage.hidden[0], storage.masks[:T].flatten(), storage.actions.flatten(),
        )
    return lp.mean().item()


def test_one_update_with_positive_advantage_increases_log_prob() -> None:
    torch.manual_seed(0)
    policy = Policy(SIZE, SIZE, hidden_size=16)
    cfg = PPOConfig(lr=1e-3, ppo_epochs=2, entropy_coef=0.0, normalize_advantage=False)
    ppo = PPO(policy, cfg)
    storage = filled_storage(policy, T=4, N=2, action=3, reward=1.0)
    storage.compute_returns(torch.zeros(2), cfg.gamma, cfg.gae_lambda)
    assert (storage.returns - storage.values[:-1] > 0).all()  # positive advantage for action 3 everywhere

    before = mean_log_prob(policy, storage)
    stats = ppo.update(storage, torch.Generator().manual_seed(0))
    after = mean_log_prob(policy, storage)
    assert after > before
    expected_keys = {"policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction", "grad_norm", "lr", "clip"}
    assert set(stats) >= expected_keys
    assert all(math.isfinite(v) for v in stats.values())


def test_update_with_normalised_advantages_prefers_the_rewarded_action() -> None:
    """Half the envs took action 1 with reward +1, the other half action 2 with reward -1."""
    torch.manual_seed(1)
    policy = Policy(SIZE, SIZE, hidden_size=16)
    cfg = PPOConfig(lr=1e-3, ppo_epochs=2, num_mini_batches=2)
    ppo = PPO(policy, cfg)
    storage = filled_storage(policy, T=4, N=4, action=1, reward=1.0)
    storage.actions[:, 2:] = 2
    storage.rewards[:, 2:] = -1.0
    T = storage.num_steps
    with torch.no_grad():  # old log-probs of the actions actually stored
        lp, _, _ = policy.evaluate_actions(
            {"view": storage.view[:T].flatten(0, 1), "target": storage.target[:T].flatten(0, 1)},
            storage.hidden[0], storage.masks[:T].flatten(), storage.actions.flatten(),
        )
    storage.log_probs.copy_(lp.view(T, 4))
    storage.compute_returns(torch.zeros(4), cfg.gamma, cfg.gae_lambda)
    ppo.update(storage, torch.Generator().manual_seed(0))
    with torch.no_grad():
        new_lp, _, _ = policy.evaluate_actions(
            {"view": storage.view[:T].flatten(0, 1), "target": storage.target[:T].flatten(0, 1)},
            storage.hidden[0], storage.masks[:T].flatten(), storage.actions.flatten(),
        )
    change = (new_lp - lp).view(T, 4)
    assert change[:, :2].mean() > 0 > change[:, 2:].mean()


def test_non_finite_loss_raises_and_leaves_weights_untouched() -> None:
    torch.manual_seed(0)
    policy = Policy(SIZE, SIZE, hidden_size=16)
    ppo = PPO(policy, PPOConfig(normalize_advantage=False))
    storage = filled_storage(policy, T=2, N=2, action=0, reward=1.0)
    storage.rewards[1, 0] = float("nan")
    storage.compute_returns(torch.zeros(2), 0.99, 0.95)
    weights = [p.detach().clone() for p in policy.parameters()]
    with pytest.raises(FloatingPointError, match="policy_loss=nan.*value_loss=nan"):
        ppo.update(storage)
    assert all(torch.equal(w, p) for w, p in zip(weights, policy.parameters()))


# --------------------------------------------------------------------------------------------------
# Linear decay, config, state
# --------------------------------------------------------------------------------------------------


def test_linear_decay_and_set_progress() -> None:
    assert linear_decay(2.5e-4, 0, 100) == pytest.approx(2.5e-4)
    assert linear_decay(2.5e-4, 50, 100) == pytest.approx(1.25e-4)
    assert linear_decay(0.2, 75, 100) == pytest.approx(0.05)
    assert linear_decay(0.2, 100, 100) == 0.0
    assert linear_decay(0.2, 150, 100) == 0.0

    policy = Policy(SIZE, SIZE, hidden_size=8)
    ppo = PPO(policy, PPOConfig())
    ppo.set_progress(7500, 30000)
    assert ppo.lr == pytest.approx(2.5e-4 * 0.75) and ppo.clip == pytest.approx(0.15)
    assert ppo.optimizer.param_groups[0]["lr"] == pytest.approx(2.5e-4 * 0.75)

    fixed = PPO(policy, PPOConfig(linear_decay=False))
    fixed.set_progress(7500, 30000)
    assert fixed.lr == 2.5e-4 and fixed.clip == 0.2

    restored = PPO(policy, PPOConfig())
    restored.load_state_dict(ppo.state_dict())
    assert restored.lr == ppo.lr and restored.optimizer.param_groups[0]["lr"] == pytest.approx(ppo.lr)


def test_ppo_config_from_yaml(repo_root) -> None:

    from findview_baselines.cli import compose_config

    from findview_baselines.cli import validate_config

    typed = validate_config(compose_config("train", ["agent=ppo"]))
    cfg = typed.trainer.ppo
    assert isinstance(cfg, PPOConfig) and typed.trainer.algorithm == "ppo"
    values = (cfg.lr, cfg.adam_eps, cfg.clip, cfg.ppo_epochs, cfg.num_mini_batches, cfg.rollout_steps)
    assert values == (2.5e-4, 1e-5, 0.2, 4, 1, 128)  # the paper's (the "0.0025" of its text is not what ran)
    assert typed.agent.sample is False and typed.agent.name == "ppo"


# --------------------------------------------------------------------------------------------------
# Difficulty scheduler
# --------------------------------------------------------------------------------------------------


def test_scheduler_levels_at_boundaries() -> None:
    sched = DifficultyScheduler(30000)
    levels = {u: sched.level(u) for u in (0, 9999, 10000, 19999, 20000, 29999, 30000, 45000)}
    assert levels == {0: 1, 9999: 1, 10000: 2, 19999: 2, 20000: 3, 29999: 3, 30000: 3, 45000: 3}
    assert sched.difficulties(1) == ("easy",)
    assert sched.difficulties(2) == ("easy", "medium")
    assert sched.difficulties(3) == ("easy", "medium", "hard")

    bounded = DifficultyScheduler(30000, mode="bounded")
    assert [bounded.difficulties(k) for k in (1, 2, 3)] == [("easy",), ("medium",), ("hard",)]

    assert DifficultyScheduler(10, num_levels=1).level(9) == 1
    with pytest.raises(ValueError, match="mode"):
        DifficultyScheduler(10, mode="sometimes")


def test_scheduler_step_and_state_dict() -> None:
    sched = DifficultyScheduler(300)
    assert sched.step(0) is False and sched.current_level == 1
    assert sched.step(99) is False
    assert sched.step(100) is True and sched.current_level == 2

    resumed = DifficultyScheduler(999, mode="bounded")
    resumed.load_state_dict(sched.state_dict())
    assert resumed.state_dict() == {
        "total_updates": 300, "num_levels": 3, "mode": "unbounded", "start_level": 1, "current_level": 2
    }
    assert resumed.level(200) == 3


def test_scheduler_can_start_at_any_level() -> None:
    """start_level 2 of 3 over 300 updates: two phases of 150 (levels 2, 3); start_level 3: hard throughout;
    a state saved before the key existed resumes at start_level 1."""
    two = DifficultyScheduler(300, start_level=2)
    assert two.current_level == 2
    assert {u: two.level(u) for u in (0, 149, 150, 299, 400)} == {0: 2, 149: 2, 150: 3, 299: 3, 400: 3}
    hard = DifficultyScheduler(300, start_level=3)
    assert {hard.level(u) for u in range(0, 300, 7)} == {3}
    assert hard.step(0) is False and hard.current_level == 3
    resumed = DifficultyScheduler(300)
    resumed.load_state_dict(hard.state_dict())
    assert resumed.level(0) == 3
    old = {"total_updates": 300, "num_levels": 3, "mode": "unbounded", "current_level": 2}
    resumed.load_state_dict(old)
    assert resumed.start_level == 1 and resumed.level(0) == 1
    with pytest.raises(ValueError, match="start_level"):
        DifficultyScheduler(300, num_levels=2, start_level=3)


# --------------------------------------------------------------------------------------------------
# Trainer sketch, end to end on a tiny fake environment
# --------------------------------------------------------------------------------------------------


class BanditEnv:
    """FindViewEnv-shaped toy: reward 1 for action RIGHT (3), else 0; episodes last ``length`` steps.

    The view shows the step count (so the policy can tell steps apart); the target is constant. With
    ``episodes_per_slot`` set, slots become inactive after that many episodes (like a static source).
    """

    def __init__(self, num_envs: int, length: int = 3, episodes_per_slot: int | None = None) -> None:
        self.num_envs = num_envs
        self.length = length
        self.episodes_per_slot = episodes_per_slot
        self.steps = torch.zeros(num_envs, dtype=torch.long)
        self.finished = torch.zeros(num_envs, dtype=torch.long)
        self.new_episode = torch.ones(num_envs, dtype=torch.bool)
        self.active = torch.ones(num_envs, dtype=torch.bool)

    def _obs(self) -> dict[str, torch.Tensor]:
        view = (self.steps * 40).to(torch.uint8).view(-1, 1, 1, 1).expand(-1, 3, SIZE, SIZE).clone()
        return {"view": view, "target": torch.full_like(view, 128)}

    def reset(self) -> dict[str, torch.Tensor]:
        self.steps.zero_()
        self.finished.zero_()
        self.new_episode.fill_(True)
        self.active.fill_(True)
        return self._obs()

    def step(self, actions: torch.Tensor):
        was_active = self.active.clone()
        reward = ((actions.cpu() == 3) & was_active).float()
        self.steps += was_active.long()
        done = (self.steps >= self.length) & was_active
        infos = [{"steps": int(self.steps[i]), "env": i} if done[i] else None for i in range(self.num_envs)]
        self.finished += done.long()
        self.steps[done] = 0
        self.new_episode = done.clone()
        if self.episodes_per_slot is not None:
            self.active = was_active & (self.finished < self.episodes_per_slot)
            self.new_episode &= self.active
        return self._obs(), reward, done, infos


def p_right(policy: Policy) -> float:
    """Mean probability of RIGHT over one 3-step bandit episode (from a zero state)."""
    obs = {
        "view": (torch.arange(3) * 40).to(torch.uint8).view(3, 1, 1, 1).expand(3, 3, SIZE, SIZE),
        "target": torch.full((3, 3, SIZE, SIZE), 128, dtype=torch.uint8),
    }
    with torch.no_grad():
        masks = torch.tensor([0.0, 1.0, 1.0])
        lp, _, _ = policy.evaluate_actions(obs, policy.initial_hidden(1), masks, torch.full((3,), 3))
    return lp.exp().mean().item()


def test_trainer_runs_rollouts_and_learns_the_bandit(tmp_path) -> None:
    from findview_baselines.rl.checkpoint import CheckpointError, load_policy, save_checkpoint
    from findview_baselines.rl.ppo_trainer import PPOTrainer

    torch.manual_seed(0)
    env = BanditEnv(num_envs=4, length=3)
    policy = Policy(SIZE, SIZE, hidden_size=16)
    assert p_right(policy) == pytest.approx(0.2, abs=0.02)
    cfg = PPOConfig(lr=2e-3, rollout_steps=6, ppo_epochs=4, num_mini_batches=2, entropy_coef=0.0)
    levels: list[int] = []
    trainer = PPOTrainer(env, policy, cfg, total_updates=9, scheduler=DifficultyScheduler(9), set_level=levels.append)
    trainer.start()

    stats = trainer.train_update()
    # 6 steps of 3-step episodes: two episodes per env, new episodes at steps 0, 3 and 6 (index 6 was
    # carried over to index 0 by after_update)
    assert len(stats["episodes"]) == 8 and stats["env_steps"] == 24 and stats["update"] == 1
    assert trainer.storage.masks[:, 0].tolist() == [0.0, 1.0, 1.0, 0.0, 1.0, 1.0, 0.0]
    for _ in range(8):
        stats = trainer.train_update()
    assert levels == [1, 2, 3] and stats["level"] == 3 and trainer.update == 9
    assert stats["lr"] == pytest.approx(2e-3 * (1 - 8 / 9))
    # the policy starts near uniform (actor gain 0.01: P(RIGHT) ~ 0.2); 9 updates push it well above
    # (0.50-0.59 over seeds 0-5)
    assert p_right(policy) > 0.35

    # checkpoints: round trip, and a mismatched model fails naming the field and the file
    path = tmp_path / "ckpt" / "last.pth"
    save_checkpoint(path, trainer.state_dict())
    other = Policy(SIZE, SIZE, hidden_size=16)
    load_policy(path, other)
    assert all(torch.equal(a, b) for a, b in zip(other.parameters(), policy.parameters()))
    resumed = PPOTrainer(env, other, cfg, total_updates=9, scheduler=DifficultyScheduler(9))
    resumed.load_state_dict(torch.load(path, weights_only=False))
    assert resumed.update == 9 and resumed.scheduler.current_level == 3
    with pytest.raises(CheckpointError, match=r"last.pth: .*hidden_size is 16 in the checkpoint but 8"):
        load_policy(path, Policy(SIZE, SIZE, hidden_size=8))


# --------------------------------------------------------------------------------------------------
# Auxiliary rotation targets in the storage and the PPO update
# --------------------------------------------------------------------------------------------------


def test_storage_aux_targets_reach_the_minibatches_time_major() -> None:
    T, N = 3, 2
    storage = make_storage(T, N)
    storage.set_initial(blank_obs(N))
    zeros = torch.zeros(N)
    for t in range(T):
        aux = torch.tensor([[t, 0.0, 1.0], [t, 1.0, 0.0]])  # env 1 has dyaw 1 and no overlap
        storage.insert(
            blank_obs(N), torch.zeros(N, 8), zeros.long(), zeros, zeros, zeros, torch.ones(N), aux_targets=aux
        )
    assert storage.has_aux_targets
    (batch,) = storage.recurrent_minibatches(torch.zeros(T, N), 1, torch.Generator().manual_seed(0))
    order = batch.env_ids.tolist()
    expected = torch.tensor([[t, float(e == 1), float(e == 0)] for t in range(T) for e in order])
    torch.testing.assert_close(batch.aux_targets, expected)

    # the next rollout without aux targets (the old call signature) gives none
    storage.after_update()
    assert not storage.has_aux_targets
    for _ in range(T):
        storage.insert(blank_obs(N), torch.zeros(N, 8), zeros.long(), zeros, zeros, zeros, torch.ones(N))
    (batch,) = storage.recurrent_minibatches(torch.zeros(T, N), 1)
    assert batch.aux_targets is None


def test_ppo_aux_loss_is_wired_and_saved() -> None:
    torch.manual_seed(0)
    policy = Policy(SIZE, SIZE, variant="correlation", hidden_size=16)
    storage = filled_storage(policy, T=4, N=2, action=3, reward=1.0)
    storage.compute_returns(torch.zeros(2), 0.99, 0.95)
    ppo = PPO(policy, PPOConfig(aux_coef=0.5, ppo_epochs=1))
    with pytest.raises(ValueError, match="aux_targets"):
        ppo.update(storage)
    storage.aux_targets.copy_(torch.tensor([0.1, -0.3, 1.0]).expand(4, 2, 3))
    storage.aux_valid.fill_(True)
    before = [p.clone() for p in ppo.aux_head.parameters()]
    stats = ppo.update(storage)
    assert math.isfinite(stats["aux_loss"]) and stats["aux_loss"] > 0
    assert 0.0 <= stats["aux_overlap_accuracy"] <= 1.0
    assert any(not torch.equal(a, b) for a, b in zip(before, ppo.aux_head.parameters()))

    state = ppo.state_dict()
    assert "aux_head" in state
    other = PPO(Policy(SIZE, SIZE, variant="correlation", hidden_size=16), PPOConfig(aux_coef=0.5))
    other.load_state_dict(state)
    assert all(torch.equal(a, b) for a, b in zip(other.aux_head.parameters(), ppo.aux_head.parameters()))
    with pytest.raises(ValueError, match="auxiliary loss"):
        PPO(Policy(SIZE, SIZE, variant="correlation", hidden_size=16), PPOConfig()).load_state_dict(state)
    # aux off (the default): no head, the state and the update are as before
    plain = PPO(policy, PPOConfig())
    assert plain.aux_head is None and "aux_head" not in plain.state_dict()
    with pytest.raises(ValueError, match="aux_coef"):
        PPO(policy, PPOConfig(aux_coef=-1.0))


def test_critic_warmup_moves_only_the_critic_then_everything() -> None:
    torch.manual_seed(0)
    policy = Policy(SIZE, SIZE, hidden_size=16)
    cfg = PPOConfig(lr=1e-3, ppo_epochs=2, critic_warmup_updates=1)
    ppo = PPO(policy, cfg)
    storage = filled_storage(policy, T=4, N=2, action=3, reward=1.0)
    storage.compute_returns(torch.zeros(2), cfg.gamma, cfg.gae_lambda)
    start = {k: v.clone() for k, v in policy.state_dict().items()}
    ppo.set_progress(0, 10)
    stats = ppo.update(storage, torch.Generator().manual_seed(0))
    assert stats["critic_warmup"] == 1.0
    changed = {k for k, v in policy.state_dict().items() if not torch.equal(v, start[k])}
    assert changed == {"critic.weight", "critic.bias"}
    ppo.set_progress(1, 10)  # warm-up over: the actor learns too
    stats = ppo.update(storage, torch.Generator().manual_seed(0))
    assert stats["critic_warmup"] == 0.0
    assert not torch.equal(policy.state_dict()["actor.weight"], start["actor.weight"])
    with pytest.raises(ValueError, match="critic_warmup_updates"):
        PPO(policy, PPOConfig(critic_warmup_updates=-1))


def test_kl_to_init_holds_the_policy_near_where_it_started_and_resumes() -> None:
    def drift(coef: float) -> tuple[float, PPO, Policy]:
        torch.manual_seed(0)
        policy = Policy(SIZE, SIZE, hidden_size=16)
        cfg = PPOConfig(lr=3e-3, ppo_epochs=4, entropy_coef=0.0, normalize_advantage=False, kl_to_init_coef=coef)
        ppo = PPO(policy, cfg)
        storage = filled_storage(policy, T=4, N=2, action=3, reward=1.0)
        storage.compute_returns(torch.zeros(2), cfg.gamma, cfg.gae_lambda)
        before = mean_log_prob(policy, storage)
        for update in range(3):
            ppo.set_progress(update, 100)
            stats = ppo.update(storage, torch.Generator().manual_seed(update))
        assert (coef > 0) == ("kl_to_init" in stats)
        return mean_log_prob(policy, storage) - before, ppo, policy

    free, _, _ = drift(0.0)
    held, ppo, policy = drift(50.0)
    assert free > 0 and 0 < held < 0.5 * free  # both learn the rewarded action; the KL term slows the drift
    # the anchor is the starting policy, not the current one, and a resumed run gets it back
    assert not torch.equal(ppo.init_policy.actor.weight, policy.actor.weight)
    assert all(not p.requires_grad for p in ppo.init_policy.parameters())
    other = PPO(Policy(SIZE, SIZE, hidden_size=16), ppo.cfg)
    other.load_state_dict(ppo.state_dict())
    for a, b in zip(ppo.init_policy.state_dict().values(), other.init_policy.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="kl_to_init_coef"):
        PPO(policy, PPOConfig(kl_to_init_coef=-1.0))
