"""PPO training loop pieces (sketch for ``tools/train.py``): rollouts, updates, evaluation, checkpoints.

The environment follows the ``findview.task.FindViewEnv`` contract (docs/ARCHITECTURE.md)::

    obs = env.reset()                                  # {"view", "target"}: (N, 3, H, W) uint8
    obs, reward, done, infos = env.step(actions)       # reward (N,), done (N,) bool, infos[i] record or None
    env.new_episode                                    # (N,) bool: obs[i] starts an episode -> mask 0
    env.active                                         # (N,) bool: slot still runs an episode (static sources)

Validation scheduling, logging and catching ``FloatingPointError`` (keep the last good checkpoint) are
left to the caller; a typical loop is::

    trainer = PPOTrainer(env, policy, PPOConfig.from_mapping(cfg.agent), total_updates, scheduler, set_level)
    trainer.start()
    for update in range(trainer.update, total_updates):
        stats = trainer.train_update()
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from findview_baselines.rl.policy import Policy, check_signature
from findview_baselines.rl.ppo import PPO, PPOConfig
from findview_baselines.rl.scheduler import DifficultyScheduler
from findview_baselines.rl.storage import RolloutStorage


def _masks(env: Any, device: torch.device) -> torch.Tensor:
    """(N,) float: 0 where the env's current observation starts a new episode."""
    return (~env.new_episode).to(device=device, dtype=torch.float32)


class PPOTrainer:
    """Collects ``rollout_steps`` steps of ``env.num_envs`` environments per update and runs PPO on them.

    Args:
        env: a batched, auto-resetting FindView environment (see module docstring).
        policy: the :class:`Policy` (already on ``device``).
        cfg: PPO hyper-parameters.
        total_updates: number of updates of the whole run (drives lr / clip decay and the scheduler).
        scheduler: optional difficulty scheduler.
        set_level: called with the new level when the scheduler levels up (and at :meth:`start`), e.g.
            ``lambda k: setattr(source, "level", k)``.
        seed: seeds the mini-batch shuffles (action sampling uses torch's global RNG: seed it in the caller).
    """

    def __init__(
        self,
        env: Any,
        policy: Policy,
        cfg: PPOConfig,
        total_updates: int,
        scheduler: DifficultyScheduler | None = None,
        set_level: Callable[[int], None] | None = None,
        seed: int = 0,
    ) -> None:
        self.env = env
        self.policy = policy
        self.cfg = cfg
        self.total_updates = total_updates
        self.scheduler = scheduler
        self.set_level = set_level
        self.device = next(policy.parameters()).device
        self.ppo = PPO(policy, cfg)
        self.storage = RolloutStorage(
            cfg.rollout_steps, env.num_envs, policy.height, policy.width, policy.hidden_size, self.device
        )
        self.shuffle_generator = torch.Generator().manual_seed(seed)
        self.update = 0  # index of the next update
        self.env_steps = 0
        self.episode_returns = torch.zeros(env.num_envs, device=self.device)

    # ---------------------------------------------------------------------------------------------

    def start(self) -> None:
        """Set the difficulty level for ``self.update`` and reset the environments."""
        if self.scheduler is not None:
            self.scheduler.step(self.update)
            if self.set_level is not None:
                self.set_level(self.scheduler.current_level)
        obs = self.env.reset()
        self.storage.set_initial(obs, _masks(self.env, self.device))
        self.episode_returns.zero_()

    @torch.no_grad()
    def collect_rollout(self) -> list[dict[str, Any]]:
        """Run ``rollout_steps`` steps, filling the storage; returns the records of finished episodes
        (each with an extra ``"return"``: the undiscounted reward sum)."""
        records: list[dict[str, Any]] = []
        self.policy.eval()
        for _ in range(self.cfg.rollout_steps):
            obs, hidden, masks = self.storage.current()
            actions, log_probs, values, new_hidden = self.policy.act(obs, hidden, masks)
            next_obs, rewards, done, infos = self.env.step(actions)
            rewards = rewards.to(self.device, torch.float32)
            self.storage.insert(
                next_obs, new_hidden, actions, log_probs, values, rewards, _masks(self.env, self.device)
            )

            self.episode_returns += rewards
            for i, info in enumerate(infos):
                if info is not None:
                    records.append({**info, "return": self.episode_returns[i].item()})
            self.episode_returns[done.to(self.device)] = 0.0
        self.env_steps += self.cfg.rollout_steps * self.env.num_envs
        return records

    def train_update(self) -> dict[str, Any]:
        """One rollout + one PPO update; returns PPO stats, level, env steps and the finished episodes.

        Raises ``FloatingPointError`` from the update (the storage is still advanced, so the caller may
        reload the last good checkpoint and call :meth:`start` again).
        """
        if self.scheduler is not None and self.scheduler.step(self.update) and self.set_level is not None:
            self.set_level(self.scheduler.current_level)
        self.ppo.set_progress(self.update, self.total_updates)

        records = self.collect_rollout()
        obs, hidden, masks = self.storage.current()
        with torch.no_grad():
            next_value = self.policy.get_value(obs, hidden, masks)
        self.storage.compute_returns(next_value, self.cfg.gamma, self.cfg.gae_lambda)
        try:
            stats: dict[str, Any] = self.ppo.update(self.storage, self.shuffle_generator)
        finally:
            self.storage.after_update()
        self.update += 1

        stats["update"] = self.update
        stats["env_steps"] = self.env_steps
        stats["level"] = self.scheduler.current_level if self.scheduler is not None else None
        stats["episodes"] = records
        return stats

    # ---------------------------------------------------------------------------------------------
    # Checkpoints
    # ---------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "signature": self.policy.model_signature(),
            "policy": self.policy.state_dict(),
            "ppo": self.ppo.state_dict(),
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else None,
            "update": self.update,
            "env_steps": self.env_steps,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Resume a run (call :meth:`start` afterwards). Raises ``ValueError`` on a model mismatch."""
        check_signature(state["signature"], self.policy.model_signature())
        self.policy.load_state_dict(state["policy"])
        self.ppo.load_state_dict(state["ppo"])
        if self.scheduler is not None and state.get("scheduler") is not None:
            self.scheduler.load_state_dict(state["scheduler"])
        self.update = int(state["update"])
        self.env_steps = int(state["env_steps"])


def save_checkpoint(path: str | Path, state: Mapping[str, Any]) -> None:
    """Write ``state`` atomically (temp file + rename), so a crash never leaves a half-written checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(dict(state), tmp)
    tmp.replace(path)


def load_policy(path: str | Path, policy: Policy) -> dict[str, Any]:
    """Load the weights of a checkpoint into ``policy`` after checking its signature; returns the checkpoint."""
    state = torch.load(path, map_location=next(policy.parameters()).device, weights_only=False)
    if "signature" not in state or "policy" not in state:
        raise ValueError(f"{path} is not a findview PPO checkpoint (no 'signature' / 'policy' entries)")
    try:
        check_signature(state["signature"], policy.model_signature())
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
    policy.load_state_dict(state["policy"])
    return state


@torch.no_grad()
def evaluate(env: Any, policy: Policy, deterministic: bool = True) -> list[dict[str, Any]]:
    """Run ``policy`` until every slot of ``env`` (a static episode source) is exhausted.

    Returns the episode records, in order of completion.
    """
    device = next(policy.parameters()).device
    policy.eval()
    obs = env.reset()
    hidden = policy.initial_hidden(env.num_envs, device)
    records: list[dict[str, Any]] = []
    while bool(env.active.any()):
        obs = {key: value.to(device) for key, value in obs.items()}
        actions, _, _, hidden = policy.act(obs, hidden, _masks(env, device), deterministic=deterministic)
        obs, _, _, infos = env.step(actions)
        records += [info for info in infos if info is not None]
    return records
