"""Run agents on a batched FindView environment and time them (the evaluation harness).

:func:`run_episodes` steps a :class:`~findview.task.FindViewEnv` (auto-reset, normally fed by a
:class:`~findview.task.StaticEpisodeSource`) with an :class:`~findview_baselines.agents.base.Agent` until
every episode is done, and returns the per-episode records (the environment's info dicts) plus the
:class:`Runtime` measurements.

Timing follows the paper's Table 12: the agent is timed alone (``agent.act``) and the environment alone
(``env.step``). ``agent_fps`` = agent decisions / agent seconds and ``env_fps`` = environment steps / env
seconds, where both counts are per environment slot (one decision / step per running episode and call).
On CUDA the device is synchronised before each clock read.
"""

from __future__ import annotations

import time
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch

__all__ = ["Runtime", "run_episodes", "TrajectoryRecorder", "TraceRecorder", "StepCallback"]

#: ``callback(env, actions)``: called after ``agent.act`` and before ``env.step`` (not timed)
StepCallback = Callable[[Any, torch.Tensor], None]


@dataclass
class Runtime:
    """Timing of one :func:`run_episodes` call.

    Attributes:
        agent_seconds: time spent in ``agent.act``.
        env_seconds: time spent in ``env.step`` (the initial ``env.reset`` is not counted).
        agent_decisions: actions produced for running episodes (one per running slot and ``act`` call).
        env_steps: environment steps of running episodes (same count as the decisions).
        episodes: finished episodes.
        wall_seconds: wall-clock time of the whole run, reset and bookkeeping included.
    """

    agent_seconds: float = 0.0
    env_seconds: float = 0.0
    agent_decisions: int = 0
    env_steps: int = 0
    episodes: int = 0
    wall_seconds: float = 0.0

    @property
    def agent_fps(self) -> float:
        """Agent decisions per second of agent time (0 when nothing was timed)."""
        return self.agent_decisions / self.agent_seconds if self.agent_seconds > 0 else 0.0

    @property
    def env_fps(self) -> float:
        """Per-slot environment steps per second of environment time (0 when nothing was timed)."""
        return self.env_steps / self.env_seconds if self.env_seconds > 0 else 0.0

    def summary(self) -> dict[str, float]:
        """``{"agent_fps", "env_fps"}`` (the ``runtime`` block of ``summary.json``)."""
        return {"agent_fps": float(self.agent_fps), "env_fps": float(self.env_fps)}

    def to_dict(self) -> dict[str, float | int]:
        """Every field plus ``agent_fps`` and ``env_fps``."""
        return {**asdict(self), **self.summary()}


class TrajectoryRecorder:
    """A :data:`StepCallback` that keeps the action sequence of chosen episodes (e.g. for videos).

    Args:
        episode_ids: the episodes to record (``None``: all of them).

    Attributes:
        actions: ``{episode_id: [action, ...]}`` for the recorded episodes (the final STOP included).
    """

    def __init__(self, episode_ids: Collection[str] | None = None) -> None:
        self.episode_ids = None if episode_ids is None else set(episode_ids)
        self.actions: dict[str, list[int]] = {}

    def __call__(self, env: Any, actions: torch.Tensor) -> None:
        slots = [
            i for i, ep in enumerate(env.episodes)
            if ep is not None and (self.episode_ids is None or ep.episode_id in self.episode_ids)
        ]
        if not slots:
            return
        active = env.active.tolist()
        acts = actions.tolist()
        for i in slots:
            if active[i]:
                self.actions.setdefault(env.episodes[i].episode_id, []).append(int(acts[i]))


class TraceRecorder:
    """A :data:`StepCallback` that keeps every episode's per-step trajectory (``tools/eval.py trace=true``).

    For each step of a running episode it records the pose *before* the step's action (``env.pitch``,
    ``env.yaw``: integer degrees; yaw in ``(-180, 180]``), the action taken and, when ``stop_prob`` gives one,
    the agent's STOP probability behind that action (``Agent.step_stop_prob``). One device-to-host copy per
    step (pose, actions, the new-episode flags and the probabilities stacked together when they share a device).

    Args:
        stop_prob: called once per step after ``agent.act``; returns ``(N,)`` probabilities (``NaN``: no value for
            that slot this step) or ``None``; e.g. ``agent.step_stop_prob``. ``None``: no probabilities.

    Attributes:
        traces: ``{episode_id: {"episode_id", "pitch", "yaw", "action", "stop_prob"}}``, one list entry per step
            (the final STOP, or the step that reached ``T``, included); ``stop_prob`` is ``None`` when the agent
            gives none, else a list of floats (7 significant digits) with ``None`` where it had no value. An
            episode id that runs again replaces its earlier trace (the episodes of an episode file have distinct
            ids).
    """

    def __init__(self, stop_prob: Callable[[], torch.Tensor | None] | None = None) -> None:
        self.stop_prob = stop_prob
        self.traces: dict[str, dict[str, Any]] = {}
        self._current: dict[int, dict[str, Any]] = {}  # slot -> the trace of the episode running there

    def __call__(self, env: Any, actions: torch.Tensor) -> None:
        probs = self.stop_prob() if self.stop_prob is not None else None
        device = env.pitch.device
        rows = torch.stack([env.pitch, env.yaw, actions.to(device).long(), env.active.long(), env.new_episode.long()])
        if probs is not None and probs.device == device:  # one copy: the integers are exact in float64
            host = torch.cat([rows.double(), probs.double()[None]]).cpu()
            pitch, yaw, acts, active, new, p = host[:5].long().tolist() + [host[5].tolist()]
        else:
            pitch, yaw, acts, active, new = rows.cpu().tolist()
            p = None if probs is None else probs.double().cpu().tolist()
        for i, ep in enumerate(env.episodes):
            if not active[i] or ep is None:
                continue
            trace = self._current.get(i)
            if new[i] or trace is None:
                trace = {"episode_id": ep.episode_id, "pitch": [], "yaw": [], "action": [],
                         "stop_prob": None if p is None else []}
                self._current[i] = self.traces[ep.episode_id] = trace
            trace["pitch"].append(int(pitch[i]))
            trace["yaw"].append(int(yaw[i]))
            trace["action"].append(int(acts[i]))
            if trace["stop_prob"] is not None:
                value = None if p is None else float(p[i])
                # 7 significant digits: a float32's precision, without the float64 digits of its conversion
                trace["stop_prob"].append(None if value is None or math.isnan(value) else float(f"{value:.7g}"))


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _limit_source(env: Any, max_episodes: int | None) -> int | None:
    """Truncate a fresh static source to ``max_episodes``; returns the number of episodes to run if known."""
    src = env.source
    episodes = getattr(src, "episodes", None)
    if isinstance(episodes, list) and getattr(src, "index", None) == 0:
        if max_episodes is not None:
            src.episodes = episodes[: int(max_episodes)]
        return len(src.episodes)
    return max_episodes


def _order_records(env: Any, records: list[dict]) -> list[dict]:
    """Records of a static source in the source's order (completion order depends on the batching)."""
    episodes = getattr(env.source, "episodes", None)
    if not isinstance(episodes, list):
        return records
    pos: dict[str, int] = {}
    for k, ep in enumerate(episodes):
        pos.setdefault(ep.episode_id, k)
    return sorted(records, key=lambda r: pos.get(r["episode_id"], len(pos)))


def run_episodes(
    env: Any,
    agent: Any,
    progress: bool = True,
    max_episodes: int | None = None,
    callbacks: Sequence[StepCallback] = (),
    desc: str | None = None,
    progress_stream: Any = None,
) -> tuple[list[dict[str, Any]], Runtime]:
    """Play every episode of ``env``'s source with ``agent``.

    Args:
        env: a :class:`~findview.task.FindViewEnv` with ``auto_reset=True``. A static source is played to
            exhaustion (``env.active`` tells which slots still run); an endless source needs
            ``max_episodes``.
        agent: a batched agent (``reset(env_ids, episodes)``, ``act(obs) -> (N,) long``); ``reset`` is
            called for the slots whose ``env.new_episode`` is set, before ``act`` sees their first
            observation, and with ``None`` episodes for slots that go idle (their source ran out).
        progress: show a tqdm progress bar (on stderr, or ``progress_stream``): finished episodes out of the
            total, with the environment steps done so far and their rate, refreshed at least every
            0.5 s, so that long episodes (up to T = 5000 steps) show movement before the first one ends.
        max_episodes: play only the first ``max_episodes`` episodes. A static source that has not
            started yet is truncated (so the same episodes run whatever ``num_envs`` is); for other
            sources the run stops after ``max_episodes`` finished episodes.
        callbacks: :data:`StepCallback` functions called every step, outside the timed sections.
        desc: progress bar label.

    Returns:
        ``(records, runtime)``: the finished episodes' records (the environment's info dicts; in the
        source's order for a static source, else in completion order) and the :class:`Runtime`.

    Raises:
        ValueError: endless source without ``max_episodes``, or ``env`` without ``auto_reset``.
    """
    if not getattr(env, "auto_reset", True):
        raise ValueError("run_episodes needs an environment with auto_reset=True")
    total = _limit_source(env, max_episodes)
    if total is None and not hasattr(env.source, "__len__"):
        raise ValueError("run_episodes: an endless episode source needs max_episodes")
    if total is None:
        total = len(env.source)
    device = torch.device(env.device)
    runtime = Runtime()
    records: list[dict[str, Any]] = []
    bar = _EpisodeBar(total, desc or getattr(agent, "name", "eval"), progress_stream) if progress else None
    t_start = time.perf_counter()
    try:
        obs = env.reset()
        while True:
            active = env.active.clone()
            n_active = int(active.sum())
            if n_active == 0 or (max_episodes is not None and len(records) >= max_episodes):
                break
            obs, finished = _step(env, agent, obs, active, n_active, callbacks, runtime, device)
            records.extend(finished)
            if bar is not None:
                bar.show(len(finished), runtime.env_steps)
    finally:
        if bar is not None:
            bar.close()
    if max_episodes is not None:
        records = records[: int(max_episodes)]
    records = _order_records(env, records)
    runtime.episodes = len(records)
    runtime.wall_seconds = time.perf_counter() - t_start
    return records, runtime


def _step(env: Any, agent: Any, obs: Any, active: torch.Tensor, n_active: int, callbacks: Sequence[StepCallback],
          runtime: Runtime, device: torch.device) -> tuple[Any, list[dict[str, Any]]]:
    """One step of every running slot: reset the agent where episodes start, time its decision and the
    environment's step, idle the agent where the source ran out; returns the new observation and the records
    of the episodes that finished."""
    new_ids = torch.nonzero(env.new_episode & active).flatten().tolist()
    if new_ids:
        agent.reset(new_ids, [env.episodes[i] for i in new_ids])
    t0 = time.perf_counter()
    actions = agent.act(obs)
    _sync(device)
    runtime.agent_seconds += time.perf_counter() - t0
    runtime.agent_decisions += n_active
    for cb in callbacks:
        cb(env, actions)
    t0 = time.perf_counter()
    obs, _, _, infos = env.step(actions)
    _sync(device)
    runtime.env_seconds += time.perf_counter() - t0
    runtime.env_steps += n_active
    # slots whose source ran out: idle the agent there (no more work for those slots)
    idle = torch.nonzero(active & ~env.active).flatten().tolist()
    if idle:
        agent.reset(idle, [None] * len(idle))
    return obs, [info for info in infos if info is not None]


class _EpisodeBar:
    """tqdm bar of finished episodes with the environment steps so far and their rate, refreshed at least
    every 0.5 s (long episodes show movement before the first one ends)."""

    def __init__(self, total: int, desc: str, stream: Any) -> None:
        from tqdm import tqdm

        self.bar = tqdm(total=total, desc=desc, unit="ep", dynamic_ncols=True, leave=True, file=stream,
                        mininterval=0.5)
        self.t_start = self.t_shown = time.perf_counter()

    def show(self, finished: int, env_steps: int) -> None:
        now = time.perf_counter()
        if finished or now - self.t_shown >= 0.5:
            self.t_shown = now
            rate = env_steps / max(now - self.t_start, 1e-9)
            self.bar.set_postfix_str(f"steps={env_steps} ({rate:.0f}/s)", refresh=False)
            self.bar.update(finished)
            self.bar.refresh()

    def close(self) -> None:
        self.bar.close()
