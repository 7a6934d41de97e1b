"""The batched FindView environment (docs/TASK.md, section Episodes).

``N`` episodes step together from one ``(N,)`` tensor of actions. All per-episode state (rotations,
targets, step counters) is a tensor on the simulator's device; panoramas live in the simulator's bank.

Host-device traffic per :meth:`FindViewEnv.step` is one device-to-host copy of a small ``(9, N)`` long
tensor (which actions were valid, which episodes ended or moved, their final rotations: what the episode
records and the Python-side episode sources need), whatever ``N``; plus, when episodes start, one
host-to-device copy of their rotations. Nothing else waits for the device.
"""

from __future__ import annotations

from typing import Callable

import torch

from findview.episode import Episode
from findview.geometry import l1_distance, wrap_yaw
from findview.runtime import light_work
from findview.sim.simulator import Simulator
from findview.task.actions import NUM_ACTIONS, Action
from findview.task.rewards import RewardConfig, compute_reward
from findview.task.sources import EpisodeSource

__all__ = ["FindViewEnv", "TargetTransform"]

# (target (3, H, W) uint8 tensor, episode) -> (3, H, W) uint8 tensor; e.g. a seeded corruption
TargetTransform = Callable[[torch.Tensor, Episode], torch.Tensor]


class FindViewEnv:
    """``N`` FindView episodes stepped together.

    Args:
        simulator: renders views (owns the device and the panorama bank).
        source: episodes to play (:class:`~findview.task.sources.StaticEpisodeSource` or
            :class:`~findview.task.sources.SampledEpisodeSource`).
        num_envs: ``N``.
        max_steps: ``T``; an episode that reaches it without STOP is force-stopped.
        pitch_bound: pitch is clamped to ``[-pitch_bound, pitch_bound]`` degrees (a move into the
            bound costs a step and changes nothing).
        step_deg: degrees per move.
        reward: reward configuration (docs/TASK.md, section Rewards).
        auto_reset: start the next episode in a slot as soon as one ends (the returned observation is
            then the new episode's first). Without it a finished slot must be :meth:`reset_envs`'d;
            stepping it is an error.
        target_transform: applied once to each new target view (e.g. a corruption), never to views. If
            it has ``info(episode) -> dict``, that dict (``corruption``, ``severity``) goes into the
            episode's record; otherwise the record says ``corruption="none"``, ``severity=0``.
        prefetch: how many upcoming episodes' panoramas to decode in the background.
    """

    @light_work()
    def __init__(
        self,
        simulator: Simulator,
        source: EpisodeSource,
        num_envs: int,
        max_steps: int = 5000,
        pitch_bound: int = 60,
        step_deg: int = 1,
        reward: RewardConfig | None = None,
        auto_reset: bool = True,
        target_transform: TargetTransform | None = None,
        prefetch: int = 8,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if max_steps < 1:
            raise ValueError(f"task.max_steps must be >= 1, got {max_steps}")
        if not 0 <= pitch_bound <= 90:
            raise ValueError(f"task.pitch_bound must be in [0, 90] degrees, got {pitch_bound}")
        if pitch_bound > simulator.pitch_bound:
            raise ValueError(f"task.pitch_bound={pitch_bound} exceeds the simulator's {simulator.pitch_bound}")
        if step_deg < 1:
            raise ValueError(f"task.step_deg must be a positive integer, got {step_deg}")
        self.sim = simulator
        self.source = source
        self.num_envs = int(num_envs)
        self.max_steps = int(max_steps)
        self.pitch_bound = int(pitch_bound)
        self.step_deg = int(step_deg)
        self.reward_cfg = reward or RewardConfig()
        self.auto_reset = auto_reset
        self.target_transform = target_transform
        self.prefetch = int(prefetch)
        self.device = simulator.device

        n, dev = self.num_envs, self.device
        z = lambda dtype=torch.long: torch.zeros(n, dtype=dtype, device=dev)  # noqa: E731
        self.pitch, self.yaw = z(), z()
        self.target_pitch, self.target_yaw = z(), z()
        self.steps, self.prev_eps, self.slots = z(), z(), z()
        self.active = z(torch.bool)  # slot holds a running episode
        self.finished = z(torch.bool)  # episode ended and (auto_reset off) not restarted yet
        self.new_episode = z(torch.bool)
        self.episodes: list[Episode | None] = [None] * n
        self._has_slot = [False] * n
        self._slot_host = [0] * n  # host copy of self.slots (no device read to release a panorama)
        # (N, H, W, 3) buffers, rendered into in place; exposed as (N, 3, H, W) channels-last views
        self._view_buf = simulator.new_buffer(n)
        self._target_buf = simulator.new_buffer(n)
        self.view = self._view_buf.permute(0, 3, 1, 2)
        self.target = self._target_buf.permute(0, 3, 1, 2)
        self.total_steps = 0

    # ----------------------------------------------------------------- public
    @property
    def observations(self) -> dict[str, torch.Tensor]:
        """``{"view", "target"}``: ``(N, 3, H, W)`` uint8 RGB, channels-last memory.

        These are the environment's own buffers, updated in place by the next :meth:`step` or reset:
        copy them (e.g. into rollout storage) to keep them.
        """
        return {"view": self.view, "target": self.target}

    @light_work()
    def reset(self) -> dict[str, torch.Tensor]:
        """Start a fresh episode in every slot; returns the first observations."""
        self._start(list(range(self.num_envs)))
        return self.observations

    @light_work()
    def reset_envs(self, env_ids: list[int]) -> dict[str, torch.Tensor]:
        """Start the next episodes in the given slots only (for ``auto_reset=False``)."""
        self._start(list(env_ids))
        return self.observations

    @light_work()
    def step(self, actions: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, list[dict | None]]:
        """Apply ``actions (N,)`` (ids of :class:`Action`); returns ``obs, reward (N,), done (N,), infos``.

        ``infos[i]`` is the finished episode's record when ``done[i]``, else ``None``. Inactive slots
        (exhausted source) ignore their action and report reward 0, done False.
        """
        a = torch.as_tensor(actions).to(self.device).long().reshape(-1)
        if a.shape[0] != self.num_envs:
            raise ValueError(f"expected {self.num_envs} actions, got shape {tuple(a.shape)}")
        if not self.auto_reset and bool((self.finished & self.active).any()):  # (finished needs auto_reset off)
            ids = torch.nonzero(self.finished & self.active).flatten().tolist()
            raise RuntimeError(
                f"envs {ids} finished their episode; call reset_envs({ids}) before stepping them (auto_reset=False)"
            )
        run = self.active
        s = self.step_deg
        dp = ((a == Action.UP).long() - (a == Action.DOWN).long()) * s * run
        dy = ((a == Action.RIGHT).long() - (a == Action.LEFT).long()) * s * run
        pitch = (self.pitch + dp).clamp(-self.pitch_bound, self.pitch_bound)
        yaw = 180 - torch.remainder(180 - (self.yaw + dy), 360)
        steps = self.steps + run.long()
        called_stop = run & (a == Action.STOP)
        forced = run & ~called_stop & (steps >= self.max_steps)
        done = called_stop | forced
        eps = l1_distance(pitch, yaw, self.target_pitch, self.target_yaw)
        moved = run & ~done & ((dp != 0) | (dy != 0))
        bad = (a < 0) | (a >= NUM_ACTIONS)
        # the step's only device -> host copy: (9, N) longs
        host = torch.stack([bad, done, moved, run, pitch, yaw, steps, eps, called_stop]).long().cpu()
        if bool(host[0].any()):  # before any state changes
            raise ValueError(f"actions must be in [0, {NUM_ACTIONS}), got {a.tolist()}")
        reward = compute_reward(self.reward_cfg, self.prev_eps, eps, called_stop, forced) * run
        self.pitch, self.yaw, self.steps, self.prev_eps = pitch, yaw, steps, eps
        self.total_steps += int(host[3].sum())

        infos: list[dict | None] = [None] * self.num_envs
        self.new_episode = torch.zeros_like(self.new_episode)
        done_ids: list[int] = torch.nonzero(host[1]).flatten().tolist()
        if done_ids:
            rec = host[4:, done_ids].tolist()  # pitch, yaw, steps, eps, called_stop of the finished ones
            for k, i in enumerate(done_ids):
                infos[i] = self._record(i, rec[0][k], rec[1][k], rec[2][k], bool(rec[4][k]), rec[3][k])
        move_ids = torch.nonzero(host[2]).flatten()
        if move_ids.numel():
            move_ids = move_ids.to(self.device, non_blocking=True)
            self.sim.render_into(
                self._view_buf, move_ids, self.slots[move_ids], self.pitch[move_ids], self.yaw[move_ids],
                validate=False,  # pitch is clamped above
            )
        if done_ids:
            if self.auto_reset:
                self._start(done_ids)
            else:
                self.finished = self.finished | done
        return self.observations, reward, done, infos

    def close(self) -> None:
        self.sim.bank.close()

    def state_dict(self) -> dict:
        """Everything needed to continue the running episodes exactly (for training resume).

        Plain Python / tensors only (loadable with ``torch.load(weights_only=True)``); includes the
        source's state when it has ``state_dict()``.
        """
        return {
            "episodes": [None if e is None else e.to_dict() for e in self.episodes],
            "pitch": self.pitch.cpu(),
            "yaw": self.yaw.cpu(),
            "steps": self.steps.cpu(),
            "active": self.active.cpu(),
            "finished": self.finished.cpu(),
            "new_episode": self.new_episode.cpu(),
            "total_steps": self.total_steps,
            "source": self.source.state_dict() if hasattr(self.source, "state_dict") else None,
        }

    def load_state_dict(self, state: dict) -> dict[str, torch.Tensor]:
        """Restore :meth:`state_dict` (same ``num_envs``); re-renders views and targets. Returns the obs."""
        if len(state["episodes"]) != self.num_envs:
            raise ValueError(f"environment state holds {len(state['episodes'])} envs, this env has {self.num_envs}")
        bank = self.sim.bank
        for i in range(self.num_envs):
            if self._has_slot[i]:
                bank.release(self._slot_host[i])
                self._has_slot[i] = False
        self.episodes = [None if e is None else Episode.from_dict(e) for e in state["episodes"]]
        dev = self.device
        self.pitch, self.yaw = state["pitch"].to(dev), state["yaw"].to(dev)
        self.steps = state["steps"].to(dev)
        self.active, self.finished = state["active"].to(dev), state["finished"].to(dev)
        self.new_episode = state["new_episode"].to(dev)
        self.total_steps = int(state["total_steps"])
        ids = [i for i, e in enumerate(self.episodes) if e is not None]
        for i in ids:
            ep = self.episodes[i]
            self._slot_host[i] = bank.acquire(ep.image)
            self.slots[i] = self._slot_host[i]
            self._has_slot[i] = True
            self.target_pitch[i], self.target_yaw[i] = ep.target_pitch, wrap_yaw(ep.target_yaw)
        self.prev_eps = l1_distance(self.pitch, self.yaw, self.target_pitch, self.target_yaw)
        if ids:
            sid = torch.tensor(ids, dtype=torch.long, device=dev)
            self.sim.render_into(self._view_buf, sid, self.slots[sid], self.pitch[sid], self.yaw[sid])
            self.sim.render_into(self._target_buf, sid, self.slots[sid], self.target_pitch[sid], self.target_yaw[sid])
            if self.target_transform is not None:
                for i in ids:
                    self.target[i].copy_(self.target_transform(self.target[i], self.episodes[i]).to(dev, torch.uint8))
        if state.get("source") is not None and hasattr(self.source, "load_state_dict"):
            self.source.load_state_dict(state["source"])
        return self.observations

    # ---------------------------------------------------------------- private
    def _record(self, i: int, pitch: int, yaw: int, steps: int, called_stop: bool, eps: int) -> dict:
        ep = self.episodes[i]
        assert ep is not None
        return {
            "episode_id": ep.episode_id,
            "image": ep.image,
            "label": ep.label,
            "difficulty": ep.difficulty,
            "init_pitch": ep.init_pitch,
            "init_yaw": ep.init_yaw,
            "target_pitch": ep.target_pitch,
            "target_yaw": ep.target_yaw,
            "final_pitch": pitch,
            "final_yaw": yaw,
            "steps": steps,
            "called_stop": called_stop,
            "eps": eps,
            "shortest_path": int(l1_distance(ep.init_pitch, ep.init_yaw, ep.target_pitch, ep.target_yaw)) + 1,
            **self._target_info(ep),
        }

    def _target_info(self, ep: Episode) -> dict:
        """``{"corruption", "severity"}`` of the episode's target (``"none"``, 0 when clean)."""
        info = getattr(self.target_transform, "info", None)
        return dict(info(ep)) if info is not None else {"corruption": "none", "severity": 0}

    def _upload(self, values: list) -> torch.Tensor:
        """A host list as a long tensor on the device, copied without waiting for queued device work."""
        return torch.tensor(values, dtype=torch.long).to(self.device, non_blocking=True)

    def _start(self, env_ids: list[int]) -> None:
        """Begin the source's next episodes in ``env_ids`` (slots whose source is exhausted go inactive)."""
        bank = self.sim.bank
        started: list[int] = []
        rows: list[list[int]] = []
        for i in env_ids:
            ep = self.source.next()
            if self._has_slot[i]:
                bank.release(self._slot_host[i])
                self._has_slot[i] = False
            self.episodes[i] = ep
            if ep is None:
                continue
            if abs(ep.init_pitch) > self.pitch_bound or abs(ep.target_pitch) > self.pitch_bound:
                raise ValueError(f"episode {ep.episode_id}: pitch outside [-{self.pitch_bound}, {self.pitch_bound}]")
            slot = bank.acquire(ep.image)
            self._slot_host[i] = slot
            self._has_slot[i] = True
            started.append(i)
            rows.append([slot, ep.init_pitch, ep.init_yaw, ep.target_pitch, ep.target_yaw])
        ids = self._upload(env_ids)
        act = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
        act[ids] = True
        self.active = torch.where(act, False, self.active)
        self.finished = torch.where(act, False, self.finished)
        if started:
            sid = self._upload(started)
            r = self._upload(rows)

            self.slots[sid], self.pitch[sid], self.yaw[sid] = r[:, 0], r[:, 1], wrap_yaw(r[:, 2])
            self.target_pitch[sid], self.target_yaw[sid] = r[:, 3], wrap_yaw(r[:, 4])
            self.steps[sid] = 0
            self.prev_eps[sid] = l1_distance(self.pitch[sid], self.yaw[sid], self.target_pitch[sid], self.target_yaw[sid])
            self.active[sid] = True
            self.new_episode[sid] = True
            # pitches were checked against the bound above: no device-side validation (a sync on CUDA)
            self.sim.render_into(self._view_buf, sid, self.slots[sid], self.pitch[sid], self.yaw[sid], validate=False)
            self.sim.render_into(
                self._target_buf, sid, self.slots[sid], self.target_pitch[sid], self.target_yaw[sid], validate=False
            )
            if self.target_transform is not None:
                for i in started:
                    t = self.target_transform(self.target[i], self.episodes[i])
                    self.target[i].copy_(t.to(self.device, torch.uint8))
        if self.prefetch > 0:
            bank.prefetch(ep.image for ep in self.source.peek(self.prefetch))
