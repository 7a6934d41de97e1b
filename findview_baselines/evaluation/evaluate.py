"""The evaluation pipeline behind ``tools/eval.py``: episodes -> environment + agent -> results.

Steps (:func:`evaluate`):

1. the episodes: ``episodes=<file>``, or ``<dataset.out_dir>/episodes/<split>_fov<sim.fov>.json`` (the
   synthetic data set is generated on first use with ``ensure_dataset``; for other data sets a missing
   file is an :class:`EvalError` quoting the ``tools/make_dataset.py`` command that makes it). Either
   way ``ensure_dataset`` checks that ``splits.json`` and the episode file were made from the root and
   settings the config names (a mismatch is one line naming the command that makes matching files), and
   a file with more episodes per image than ``dataset.episodes_per_image`` serves its first ``K`` per
   image per difficulty. Then filtered by ``difficulty`` and cut to ``max_episodes``;
2. the simulator and a batched, auto-resetting :class:`~findview.task.FindViewEnv` over a
   :class:`~findview.task.StaticEpisodeSource`;
3. the agent (``make_agent(agent.name, ...)``, or a PPO checkpoint with ``checkpoint=<path>``);
4. :func:`~findview_baselines.evaluation.harness.run_episodes`, then the optional videos, then the
   result files (all written atomically, only once every episode is done; with ``trace=true`` also
   ``traces.jsonl``, each episode's poses, actions and STOP probabilities step by step).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Union

from findview.episode import DIFFICULTIES, Episode
from findview_baselines.config import EvalConfig, PPOAgentConfig, RenderCorruptionsConfig, RenderEpisodeConfig
from findview_baselines.errors import UserError

log = logging.getLogger("findview.eval")

__all__ = [
    "EvalError",
    "EpisodeToolConfig",
    "override_values",
    "override_keys",
    "checkpoint_implies_agent",
    "make_dataset_command",
    "resolve_episodes",
    "filter_episodes",
    "build_env",
    "apply_checkpoint_config",
    "build_agent",
    "render_videos",
    "evaluate",
]

#: the typed configs of the tools that read a split's static episodes (``dataset``, ``sim``, ``task``, ``split``)
EpisodeToolConfig = Union[EvalConfig, RenderEpisodeConfig, RenderCorruptionsConfig]

#: the keys of a learned agent's checkpoint signature that are fields of its agent config (the model)
_MODEL_KEYS = ("variant", "hidden_size", "fine_shifts", "fine_scales")
#: the learned agent's search-memory settings (a training run records the ones it validated with)
_SEARCH_KEYS = ("revisit_penalty", "revisit_row_stride", "revisit_row_after", "revisit_row_budget", "revisit_row_hold",
                "revisit_near_rows", "revisit_near_penalty", "revisit_near_age", "revisit_near_since",
                "revisit_near_until")
#: the learned agent's settings that change what its network reads, which a training run trains with
_TRAINED_KEYS = ("wide_match_min_peak",)


class EvalError(UserError):
    """A user-facing configuration / input problem (the tools print the message, no traceback)."""


def override_values(overrides: Sequence[str]) -> dict[str, str]:
    """``{key: value}`` of the ``key=value`` overrides of a command line (``+`` / ``~`` prefixes dropped, flags
    ignored; a later override of a key wins). The one parser of overrides of this module."""
    return {o.split("=", 1)[0].lstrip("+~"): o.split("=", 1)[1] for o in overrides if "=" in o and not o.startswith("-")}


def override_keys(overrides: Sequence[str]) -> set[str]:
    """The keys a command line sets: ``sim.fov`` for ``sim.fov=60``, ``agent`` for a group choice ``agent=sift``."""
    return set(override_values(overrides))


def checkpoint_implies_agent(argv: list[str]) -> list[str]:
    """``tools/eval.py`` arguments with ``agent=ppo`` added when ``checkpoint=<path>`` is given without an
    ``agent=`` choice, so that the learned agent's keys (``agent.revisit_penalty=0``, ...) are valid
    overrides in every job (for :func:`findview_baselines.cli.run_tool`'s ``implied``)."""
    values = override_values(argv)
    if values.get("checkpoint", "") not in ("", "null", "None") and "agent" not in values:
        return [*argv, "agent=ppo"]
    return argv


def make_dataset_command(cfg: EpisodeToolConfig, dataset_choice: str | None = None, overrides: Sequence[str] = ()) -> str:
    """The ``tools/make_dataset.py`` command that writes the episode file this evaluation needs.

    It repeats the ``dataset`` choice and the eval command's overrides that shape the episode files
    (``dataset.*``, ``sim`` / ``sim.fov``; ``task.pitch_bound`` as ``dataset.episode_pitch_bound``), and adds
    ``sim.fov`` / ``dataset.splits_to_make`` when the data set config would not make this FoV / split.
    """
    ds = cfg.dataset
    parts = ["python tools/make_dataset.py", f"dataset={dataset_choice or ds.name}"]
    given = override_keys(overrides)
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if key.startswith("dataset.") or key in ("sim", "sim.fov"):
            parts.append(o)
        elif key == "task.pitch_bound" and "dataset.episode_pitch_bound" not in given:
            parts.append(f"dataset.episode_pitch_bound={o.split('=', 1)[1]}")
    if "dataset.root" not in given and ds.kind != "synthetic" and not ds.root:
        parts.append("dataset.root=<folder with the panoramas>")
    fov = float(cfg.sim.fov)
    if not given & {"sim", "sim.fov", "dataset.episode_fovs"} and fov not in [float(f) for f in ds.episode_fovs]:
        parts.append(f"sim.fov={fov:g}")
    splits = [str(s) for s in ds.splits_to_make]
    if "dataset.splits_to_make" not in given and cfg.split not in splits:
        parts.append(f"dataset.splits_to_make=[{','.join([*splits, cfg.split])}]")
    return " ".join(parts)


def resolve_episodes(
    cfg: EpisodeToolConfig,
    dataset_choice: str | None = None,
    overrides: Sequence[str] = (),
    logger: logging.Logger | None = None,
    progress: bool = True,
    episodes_file: str | None = None,
) -> tuple[list[Episode], Path, str]:
    """Load the episodes to evaluate. Returns ``(episodes, episode file, data set name)``.

    ``logger``: where progress lines go (the calling tool's logger; default ``findview.eval``); ``progress``:
    tqdm bars while a synthetic data set is made; ``episodes_file``: an explicit episode file (the tool's
    ``episodes=``) instead of the split's.

    Raises:
        EvalError: missing / broken episode file (with the command that makes it).
    """
    from findview.dataset import SamplingError, ensure_dataset
    from findview.dataset.episodes import episode_file, load_episodes, read_episode_file

    fov = float(cfg.sim.fov)
    if episodes_file:
        path = Path(os.path.expanduser(str(episodes_file)))
        if not path.is_file():
            raise EvalError(f"episode file not found: {path} (episodes=...)")
        header = read_episode_file(path)  # the file's header: data, read by key
        file_fov = header.get("fov")
        if file_fov is not None and float(file_fov) != fov:
            (logger or log).warning("episode file %s was sampled for FoV %g but sim.fov=%g", path, float(file_fov), fov)
        return load_episodes(path), path, str(header.get("dataset", path.stem))
    ds, split = cfg.dataset, cfg.split
    if not ds.out_dir:
        raise EvalError(f"dataset.out_dir is not set for data set {ds.name!r}")
    out_dir = os.path.abspath(os.path.expanduser(str(ds.out_dir)))
    path = episode_file(out_dir, split, fov)
    if ds.kind != "synthetic" and not path.is_file():  # only synthetic data is made here
        raise EvalError(
            f"no {split} episodes for data set {ds.name!r} at FoV {fov:g}: {path} does not exist.\n"
            f"Make them with:\n  {make_dataset_command(cfg, dataset_choice, overrides)}"
        )
    # the files must come from the root and settings the config names (synthetic: made when missing)
    try:
        out_dir = str(ensure_dataset(ds, [fov], pitch_bound=cfg.task.pitch_bound, progress=progress,
                                     log=(logger or log).info, splits=[split]))
    except SamplingError as err:  # SamplingError is a RuntimeError: give it the data set's context
        raise EvalError(f"cannot make the episodes of data set {ds.name!r}: {err}") from err
    path = episode_file(out_dir, split, fov)  # ensure_dataset made it or found it
    return load_episodes(path, episodes_per_image=ds.episodes_per_image), path, ds.name


def filter_episodes(episodes: Sequence[Episode], difficulty: Any = None, max_episodes: int | None = None) -> list[Episode]:
    """Keep one difficulty (``None``/``"all"``: all; also a list of names) and the first ``max_episodes``."""
    out = list(episodes)
    if difficulty not in (None, "", "all"):
        wanted = [str(d) for d in difficulty] if isinstance(difficulty, (list, tuple)) else [str(difficulty)]
        bad = [d for d in wanted if d not in DIFFICULTIES]
        if bad:
            raise EvalError(f"unknown difficulty {bad[0]!r}; valid: {', '.join(DIFFICULTIES)} (or null for all)")
        out = [e for e in out if e.difficulty in wanted]
    if max_episodes is not None:
        if int(max_episodes) < 1:
            raise EvalError(f"max_episodes must be >= 1, got {max_episodes}")
        out = out[: int(max_episodes)]
    return out


def build_env(cfg: EvalConfig, episodes: Sequence[Episode], num_envs: int):
    """Simulator + auto-resetting environment over the static episodes (:func:`findview.build.build_static_env`),
    with the ``corruption`` section's target corruption."""
    from findview.build import build_static_env

    try:
        return build_static_env(cfg.sim, cfg.task, episodes, num_envs, corruption_cfg=cfg.corruption)
    except ValueError as err:
        raise EvalError(str(err)) from err


def _corruption_label(cfg: EvalConfig) -> str:
    """The ``corruption.name`` setting as text (``none`` when clean)."""
    name = cfg.corruption.name
    return ",".join(str(n) for n in name) if isinstance(name, (list, tuple)) else str(name)


def config_yaml(cfg: EvalConfig) -> str:
    """The YAML text of a typed config (every value as the run used it)."""
    from omegaconf import OmegaConf

    return OmegaConf.to_yaml(OmegaConf.structured(cfg))


def _rewrite_hydra_config(out: Path, cfg: EvalConfig) -> None:
    """Replace ``.hydra/config.yaml`` by the effective config (after a checkpoint supplied the agent and the
    view), so that the run folder never shows the default agent's config beside a checkpoint's results."""
    from findview.utils import write_text

    path = out / ".hydra" / "config.yaml"
    if path.is_file():
        write_text(path, config_yaml(cfg))


def apply_checkpoint_config(cfg: EvalConfig, overrides: Sequence[str] = ()) -> EvalConfig:
    """``checkpoint=...``: the config with the FoV, the view size and the agent's model of the checkpoint.

    ``sim.fov`` / ``sim.height`` / ``sim.width`` come from the checkpoint (the view size its run rendered,
    an integer multiple of its network's with ``agent.downsample``) unless given on the command line
    (or a ``sim=`` preset was chosen), and ``agent.fov`` follows ``sim.fov`` unless given; ``agent`` becomes a learned-agent config with the checkpoint's model
    (keeping ``agent.sample`` when the learned agent was chosen); the search memory (``agent.revisit_penalty``,
    ``agent.revisit_row_*``, ``agent.revisit_near_*``) and the wide match's peak gate (``agent.wide_match_min_peak``)
    are the command line's, else the training run's, else the schema's. ``cfg`` itself is not changed.

    Raises:
        EvalError: ``agent=<a rule-based agent>`` was given with the checkpoint (the one place this is checked).
        CheckpointNotFound, CheckpointError: the file is missing, a folder or not a findview checkpoint
            (naming it, what it is and what was expected).
    """
    from findview_baselines.rl.checkpoint import load_checkpoint

    given = override_keys(overrides)
    learned = isinstance(cfg.agent, PPOAgentConfig)
    if not learned and "agent" in given:
        raise EvalError(f"checkpoint= evaluates a learned agent; it cannot be combined with agent={cfg.agent.name} "
                        f"(use agent=ppo or drop agent=)")
    state = load_checkpoint(os.path.expanduser(str(cfg.checkpoint)), key="checkpoint")  # user errors if unusable
    sig = dict(state["signature"])  # checkpoint contents: read by key
    run_conf = dict(state.get("config") or {})
    trained_sim, trained_agent = dict(run_conf.get("sim") or {}), dict(run_conf.get("agent") or {})
    # the size the run rendered (a multiple of the network's with agent.downsample), else the network's
    rendered = trained_sim if all(k in trained_sim for k in ("height", "width")) else sig
    view = {k: int(rendered[k]) for k in ("height", "width") if k in rendered and not given & {"sim", f"sim.{k}"}}
    if "fov" in trained_sim and not given & {"sim", "sim.fov"}:
        view["fov"] = float(trained_sim["fov"])
    model: dict[str, Any] = {k: sig[k] for k in _MODEL_KEYS if k in sig}
    model["memory_inputs"] = bool(sig.get("memory_inputs", 0))  # a width in the signature, a switch in the config
    model["pitch_warps"] = bool(sig.get("pitch_warps", 0))
    model["wide_match"] = bool(sig.get("wide_match", 0))
    search = {k: trained_agent[k] for k in (*_SEARCH_KEYS, *_TRAINED_KEYS)
              if k in trained_agent and f"agent.{k}" not in given}
    # agent.fov (the refinement's degrees per pixel, the search memory's band) follows the FoV the views will have
    fov = {} if "agent.fov" in given else {"fov": float(view.get("fov", cfg.sim.fov))}
    agent = replace(cfg.agent if learned else PPOAgentConfig(), **model, **search, **fov)
    return replace(cfg, sim=replace(cfg.sim, **view), agent=agent)


def build_agent(cfg: EvalConfig, num_envs: int, device: Any):
    """The agent of the ``agent`` section (with ``checkpoint``: the learned agent of that checkpoint, whose
    config :func:`apply_checkpoint_config` made). Returns ``(agent, name)``.

    Raises:
        EvalError: unknown agent (listing the valid names), unusable checkpoint, ``agent=ppo`` without one.
    """
    import findview_baselines.agents.ppo_agent  # noqa: F401  (registers "ppo")
    from findview_baselines.agents import agent_names, make_agent

    name = "ppo" if cfg.checkpoint else cfg.agent.name
    context: dict[str, Any] = {}
    if cfg.checkpoint:
        context = {"checkpoint": os.path.expanduser(str(cfg.checkpoint)), "height": cfg.sim.height,
                   "width": cfg.sim.width}
    elif name == "ppo":
        raise EvalError("agent=ppo needs a trained policy: pass checkpoint=<path to a .pth checkpoint>")
    agent_cfg = cfg.agent
    if isinstance(agent_cfg, PPOAgentConfig) and agent_cfg.stop_by > cfg.task.max_steps:
        log.warning("agent.stop_by=%d is beyond task.max_steps=%d: the agent stops by step %d", agent_cfg.stop_by,
                    cfg.task.max_steps, cfg.task.max_steps)
        agent_cfg = replace(agent_cfg, stop_by=cfg.task.max_steps)
    try:
        agent = make_agent(name, agent_cfg, num_envs, device, cfg.seed, **context)
    except (FileNotFoundError, ValueError) as err:
        msg = str(err)
        if name not in agent_names():
            msg = f"unknown agent {name!r} (agent.name in the agent config); valid agents: {', '.join(agent_names())}"
        raise EvalError(msg) from err
    return agent, name


def render_videos(
    cfg: EvalConfig, out_dir: Path, episodes: Sequence[Episode], records: Sequence[Mapping[str, Any]],
    actions: Mapping[str, list[int]],
) -> list[Path]:
    """``videos/<episode_id>.mp4`` for the recorded episodes (replayed from their actions)."""
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.viz import replay_rotations, write_video

    by_id = {r["episode_id"]: r for r in records}
    sim, task = cfg.sim, cfg.task
    written = []
    for ep in episodes:
        acts = actions.get(ep.episode_id)
        rec = by_id.get(ep.episode_id)
        if acts is None or rec is None:
            continue
        rots = replay_rotations((ep.init_pitch, ep.init_yaw), acts, task.pitch_bound, task.step_deg)
        if rots[-1] != (rec["final_pitch"], rec["final_yaw"]) or len(acts) != rec["steps"]:
            log.warning("episode %s: replayed trajectory does not match its record; video skipped", ep.episode_id)
            continue
        pano = load_panorama(ep.image)
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in ep.episode_id)
        path = write_video(
            out_dir / "videos" / f"{safe}.mp4", pano, rots, (ep.target_pitch, ep.target_yaw),
            float(sim.fov), sim.height, sim.width, sim.mode, float(cfg.video_fps), cfg.video_pano_height,
        )
        written.append(path)
    return written


def _run_meta(cfg: EvalConfig, dataset_name: str, path: Path, agent_config: str, episodes: int, num_envs: int,
              device: Any) -> dict[str, Any]:
    """The settings of an evaluation run that ``run.json`` and the tables record."""
    corruption = _corruption_label(cfg)
    return {
        "dataset": dataset_name,
        "split": cfg.split if not cfg.episodes else Path(path).stem,
        "agent_config": agent_config,
        "corruption": corruption,
        "severity": cfg.corruption.severity if corruption != "none" else 0,
        "difficulty": cfg.difficulty,
        "episodes_file": str(path),
        "episodes": episodes,
        "fov": float(cfg.sim.fov),
        "view": f"{cfg.sim.height}x{cfg.sim.width}",
        "num_envs": num_envs,
        "seed": cfg.seed,
        "device": str(device),
        "checkpoint": cfg.checkpoint,
    }


def _play(cfg: EvalConfig, episodes: list[Episode], num_envs: int, device: Any, out: Path, where: str):
    """Agent and environment over ``episodes``; returns ``(records, runtime, agent name, trajectory recorder,
    trace recorder)`` (the recorders ``None`` unless ``video`` / ``trace`` asked for them)."""
    from findview_baselines.evaluation.harness import TraceRecorder, TrajectoryRecorder, run_episodes

    agent, agent_name = build_agent(cfg, num_envs, device)  # fail fast on agent errors
    env = None
    try:
        env = build_env(cfg, episodes, num_envs)
        recorder = TrajectoryRecorder([e.episode_id for e in episodes[: cfg.video]]) if cfg.video else None
        tracer = TraceRecorder(agent.step_stop_prob) if cfg.trace else None
        log.info("evaluating %d episodes of %s with %s on %s, %d envs; results -> %s",
                 len(episodes), where, agent_name, env.device, num_envs, out)
        callbacks = [cb for cb in (recorder, tracer) if cb is not None]
        records, runtime = run_episodes(env, agent, progress=cfg.progress, callbacks=callbacks, desc=agent_name)
    finally:
        if hasattr(agent, "close"):
            agent.close()
        if env is not None:
            env.close()
    return records, runtime, agent_name, recorder, tracer


def evaluate(
    cfg: EvalConfig,
    out_dir: str | os.PathLike,
    choices: Mapping[str, str] | None = None,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """Run one evaluation and write its results into ``out_dir``; returns the summary.

    Args:
        cfg: the validated ``eval`` config (a composed ``DictConfig`` is validated first).
        out_dir: the run folder.
        choices: Hydra's config-group choices (``{"agent": "sift", "dataset": "folder", ...}``).
        overrides: the command-line overrides (what the user set: the make_dataset hint, the keys a
            checkpoint does not replace, an explicit ``agent=``).
    """
    from findview.sim import resolve_device
    from findview_baselines.config import typed_config
    from findview_baselines.evaluation.results import write_results

    cfg = typed_config(cfg)
    choices = dict(choices or {})
    out = Path(out_dir)
    if cfg.checkpoint:
        cfg = apply_checkpoint_config(cfg, overrides)
        choices["agent"] = "ppo"
        _rewrite_hydra_config(out, cfg)
    episodes, path, dataset_name = resolve_episodes(cfg, choices.get("dataset"), overrides, progress=cfg.progress,
                                                    episodes_file=cfg.episodes)
    if not episodes:
        raise EvalError(f"{path} holds no episodes (does the split have images? see its splits.json)")
    episodes = filter_episodes(episodes, cfg.difficulty, cfg.max_episodes)
    if not episodes:
        raise EvalError(f"{path} holds no {cfg.difficulty} episodes")
    num_envs = min(cfg.num_envs, len(episodes))
    try:
        device = resolve_device(str(cfg.sim.device))
    except ValueError as err:
        raise EvalError(str(err)) from err
    records, runtime, agent_name, recorder, tracer = _play(cfg, episodes, num_envs, device, out,
                                                           f"{dataset_name} ({path})")
    if recorder is not None:
        for p in render_videos(cfg, out, episodes, records, recorder.actions):
            log.info("video: %s", p)
    meta = _run_meta(cfg, dataset_name, path, choices.get("agent", agent_name), len(records), num_envs, device)
    summary = write_results(out, records, runtime.to_dict(), agent_name, meta, config_yaml(cfg),
                            traces=tracer.traces if tracer is not None else None)
    log.info("summary: %s", out / "summary.md")
    return summary
