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
   result files (all written atomically, only once every episode is done).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from findview.episode import DIFFICULTIES, Episode
from findview_baselines.errors import UserError

log = logging.getLogger("findview.eval")

__all__ = [
    "EvalError",
    "checkpoint_implies_agent",
    "make_dataset_command",
    "resolve_episodes",
    "filter_episodes",
    "build_env",
    "build_agent",
    "render_videos",
    "evaluate",
]


class EvalError(UserError):
    """A user-facing configuration / input problem (the tools print the message, no traceback)."""


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    try:
        value = OmegaConf.select(cfg, key, default=default) if isinstance(cfg, DictConfig) else cfg.get(key, default)
    except Exception:
        return default
    return default if value is None else value


def checkpoint_implies_agent(argv: list[str]) -> list[str]:
    """``tools/eval.py`` arguments with ``agent=ppo`` added when ``checkpoint=<path>`` is given without an
    ``agent=`` choice, so that the learned agent's keys (``agent.revisit_penalty=0``, ...) are valid
    overrides in every job (for :func:`findview_baselines.cli.run_tool`'s ``implied``)."""
    def key_value(arg: str) -> tuple[str, str]:
        key, _, value = arg.partition("=")
        return key.lstrip("+~"), value

    args = [key_value(a) for a in argv if not a.startswith("-") and "=" in a]
    has_checkpoint = any(k == "checkpoint" and v not in ("", "null", "None") for k, v in args)
    if has_checkpoint and not any(k == "agent" for k, _ in args):
        return [*argv, "agent=ppo"]
    return argv


def make_dataset_command(cfg: DictConfig, dataset_choice: str | None = None, overrides: Sequence[str] = ()) -> str:
    """The ``tools/make_dataset.py`` command that writes the episode file this evaluation needs.

    It repeats the ``dataset`` choice and the eval command's overrides that shape the episode files
    (``dataset.*``, ``sim`` / ``sim.fov``; ``task.pitch_bound`` as ``dataset.episode_pitch_bound``), and adds
    ``sim.fov`` / ``dataset.splits_to_make`` when the data set config would not make this FoV / split.
    """
    name = dataset_choice or str(_get(cfg, "dataset.name", "<name>"))
    parts = ["python tools/make_dataset.py", f"dataset={name}"]
    given: set[str] = set()
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if key.startswith("dataset.") or key in ("sim", "sim.fov"):
            parts.append(o)
            given.add(key)
        elif key == "task.pitch_bound" and "dataset.episode_pitch_bound" not in given:
            parts.append(f"dataset.episode_pitch_bound={o.split('=', 1)[1]}")
    if "dataset.root" not in given and _get(cfg, "dataset.kind") != "synthetic" and _get(cfg, "dataset.root") in (None, "", "???"):
        parts.append("dataset.root=<folder with the panoramas>")
    fov = float(_get(cfg, "sim.fov", 90))
    fovs = _get(cfg, "dataset.episode_fovs")
    if fovs is not None and not given & {"sim", "sim.fov", "dataset.episode_fovs"}:
        fovs = [float(f) for f in (fovs if OmegaConf.is_list(fovs) or isinstance(fovs, Sequence) else [fovs])]
        if fov not in fovs:
            parts.append(f"sim.fov={fov:g}")
    splits = _get(cfg, "dataset.splits_to_make")
    split = str(_get(cfg, "split", "test"))
    if splits is not None and "dataset.splits_to_make" not in given:
        splits = [str(s) for s in (splits if OmegaConf.is_list(splits) or isinstance(splits, Sequence) else [splits])]
        if split not in splits:
            parts.append(f"dataset.splits_to_make=[{','.join([*splits, split])}]")
    return " ".join(parts)


def resolve_episodes(
    cfg: DictConfig, dataset_choice: str | None = None, overrides: Sequence[str] = (), logger: logging.Logger | None = None
) -> tuple[list[Episode], Path, str]:
    """Load the episodes to evaluate. Returns ``(episodes, episode file, data set name)``.

    ``logger``: where progress lines go (the calling tool's logger; default ``findview.eval``).

    Raises:
        EvalError: missing / broken episode file (with the command that makes it).
    """
    from findview.dataset.episodes import episode_file, load_episodes, read_episode_file

    fov = float(_get(cfg, "sim.fov", 90))
    explicit = _get(cfg, "episodes")
    if explicit:
        path = Path(os.path.expanduser(str(explicit)))
        if not path.is_file():
            raise EvalError(f"episode file not found: {path} (episodes=...)")
        header = read_episode_file(path)
        name = str(header.get("dataset", path.stem))
        file_fov = header.get("fov")
        if file_fov is not None and float(file_fov) != fov:
            (logger or log).warning("episode file %s was sampled for FoV %g but sim.fov=%g", path, float(file_fov), fov)
    else:
        if "dataset" not in cfg or cfg.dataset is None:
            raise EvalError("no data set configured: pass dataset=<name> or episodes=<episode file>")
        name = str(_get(cfg, "dataset.name", dataset_choice or "?"))
        split = str(_get(cfg, "split", "test"))
        out_dir = _get(cfg, "dataset.out_dir")
        if out_dir in (None, "", "???"):
            raise EvalError(f"dataset.out_dir is not set for data set {name!r}")
        out_dir = os.path.abspath(os.path.expanduser(str(out_dir)))
        path = episode_file(out_dir, split, fov)
        if _get(cfg, "dataset.kind") != "synthetic" and not path.is_file():  # only synthetic data is made here
            raise EvalError(
                f"no {split} episodes for data set {name!r} at FoV {fov:g}: {path} does not exist.\n"
                f"Make them with:\n  {make_dataset_command(cfg, dataset_choice, overrides)}"
            )
        from findview.dataset import SamplingError, dataset_settings, ensure_dataset

        # the files must come from the root and settings the config names (synthetic: made when missing)
        try:
            out_dir = str(
                ensure_dataset(
                    cfg.dataset, [fov], pitch_bound=int(_get(cfg, "task.pitch_bound", 60)),
                    progress=bool(_get(cfg, "progress", True)), log=(logger or log).info, splits=[split],
                )
            )
        except SamplingError as err:  # SamplingError is a RuntimeError: give it the data set's context
            raise EvalError(f"cannot make the episodes of data set {name!r}: {err}") from err
        path = episode_file(out_dir, split, fov)  # ensure_dataset made it or found it
        return load_episodes(path, episodes_per_image=dataset_settings(cfg.dataset)["episodes_per_image"]), path, name
    return load_episodes(path), path, name


def filter_episodes(episodes: Sequence[Episode], difficulty: Any = None, max_episodes: Any = None) -> list[Episode]:
    """Keep one difficulty (``None``/``"all"``: all; also a list of names) and the first ``max_episodes``."""
    out = list(episodes)
    if difficulty not in (None, "", "all"):
        wanted = [str(d) for d in difficulty] if isinstance(difficulty, (list, tuple)) or OmegaConf.is_list(difficulty) else [str(difficulty)]
        bad = [d for d in wanted if d not in DIFFICULTIES]
        if bad:
            raise EvalError(f"unknown difficulty {bad[0]!r}; valid: {', '.join(DIFFICULTIES)} (or null for all)")
        out = [e for e in out if e.difficulty in wanted]
    if max_episodes is not None:
        n = int(max_episodes)
        if n < 1:
            raise EvalError(f"max_episodes must be >= 1, got {max_episodes}")
        out = out[:n]
    return out


def build_env(cfg: DictConfig, episodes: Sequence[Episode], num_envs: int):
    """Simulator + auto-resetting environment over the static episodes (:func:`findview.build.build_static_env`),
    with the ``corruption`` section's target corruption."""
    from findview.build import build_static_env

    try:
        return build_static_env(cfg.sim, cfg.task, episodes, num_envs, corruption_cfg=_get(cfg, "corruption"))
    except ValueError as err:
        raise EvalError(str(err)) from err


def _corruption_label(cfg: DictConfig) -> str:
    """The ``corruption.name`` setting as text (``none`` when clean)."""
    name = _get(cfg, "corruption.name", "none")
    if OmegaConf.is_list(name) or isinstance(name, (list, tuple)):
        return ",".join(str(n) for n in name)
    return str(name)


def _rewrite_hydra_config(out: Path, cfg: DictConfig) -> None:
    """Replace ``.hydra/config.yaml`` by the effective config (after a checkpoint supplied the agent and the
    view), so that the run folder never shows the default agent's config beside a checkpoint's results."""
    from findview.utils import write_text

    path = out / ".hydra" / "config.yaml"
    if path.is_file():
        write_text(path, OmegaConf.to_yaml(cfg))


def _overridden(overrides: Sequence[str], *keys: str) -> bool:
    return any(o.split("=", 1)[0].lstrip("+~") in keys for o in overrides)


def apply_checkpoint_config(cfg: DictConfig, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """``checkpoint=...``: take the FoV, the view size and the agent's model from the checkpoint.

    ``sim.fov`` / ``sim.height`` / ``sim.width`` come from the checkpoint unless given on the command
    line (or a ``sim=`` preset was chosen); ``cfg.agent`` becomes the checkpoint's learned-agent config
    (keeping ``agent.sample`` when ``agent=ppo`` was given; ``agent.revisit_penalty`` from the command line,
    else the training run's). Edits ``cfg`` in place; returns the
    checkpoint's run config (``{}`` when it has none).

    Raises:
        CheckpointNotFound, CheckpointError: the file is missing, a folder or not a findview checkpoint
            (naming it, what it is and what was expected).
    """
    from omegaconf import open_dict

    from findview_baselines.agents.revisit import search_settings
    from findview_baselines.rl.checkpoint import load_checkpoint

    path = os.path.expanduser(str(_get(cfg, "checkpoint")))
    state = load_checkpoint(path, key="checkpoint")  # CheckpointError / CheckpointNotFound: user errors
    run_conf = dict(state.get("config") or {})
    sig = dict(state["signature"])
    trained_sim = dict(run_conf.get("sim") or {})
    with open_dict(cfg):
        if not _overridden(overrides, "sim", "sim.height"):
            cfg.sim.height = int(sig.get("height", cfg.sim.height))
        if not _overridden(overrides, "sim", "sim.width"):
            cfg.sim.width = int(sig.get("width", cfg.sim.width))
        if "fov" in trained_sim and not _overridden(overrides, "sim", "sim.fov"):
            cfg.sim.fov = float(trained_sim["fov"])
        sample = bool(_get(cfg, "agent.sample", False)) if _get(cfg, "agent.name") == "ppo" else False
        # the search memory: a key given on the command line, else the setting the run validated with
        search = search_settings(dict(run_conf.get("agent") or {}))
        search.update({k: v for k, v in search_settings(cfg.agent).items() if _overridden(overrides, f"agent.{k}")})
        cfg.agent = OmegaConf.create({
            "name": "ppo",
            "variant": str(sig.get("variant", "early_fusion")),
            "hidden_size": int(sig.get("hidden_size", 512)),
            "sample": sample,
            **search,
        })
    return run_conf


def build_agent(cfg: DictConfig, num_envs: int, device: Any, agent_explicit: bool = True):
    """The agent named by ``agent.name`` (or the PPO policy of ``checkpoint``). Returns ``(agent, name)``.

    Raises:
        EvalError: unknown agent (listing the valid names), bad agent keys, unusable checkpoint.
    """
    from findview_baselines.agents import agent_names, make_agent
    from findview_baselines.agents.ppo_agent import PPOAgent
    from findview_baselines.agents.revisit import search_settings

    name = str(_get(cfg, "agent.name", "?"))
    checkpoint = _get(cfg, "checkpoint")
    seed = int(_get(cfg, "seed", 0))
    if checkpoint:
        if name != "ppo" and agent_explicit:
            raise EvalError(f"checkpoint= evaluates a PPO policy; it cannot be combined with agent={name} (use agent=ppo or drop agent=)")
        sample = bool(_get(cfg, "agent.sample", False)) if name == "ppo" else False
        try:
            agent = PPOAgent.from_checkpoint(
                os.path.expanduser(str(checkpoint)), num_envs, device, seed, bool(sample),
                height=int(_get(cfg, "sim.height", 256)), width=int(_get(cfg, "sim.width", 256)),
                **search_settings(cfg.agent),
            )
        except (FileNotFoundError, ValueError) as err:
            raise EvalError(str(err)) from err
        return agent, "ppo"
    if name == "ppo":
        raise EvalError("agent=ppo needs a trained policy: pass checkpoint=<path to a .pth checkpoint>")
    try:
        agent = make_agent(name, cfg.agent, num_envs, device, seed)
    except ValueError as err:
        msg = str(err)
        if name not in agent_names():
            msg = f"unknown agent {name!r} (agent.name in the agent config); valid agents: {', '.join(agent_names())}"
        raise EvalError(msg) from err
    return agent, name


def render_videos(
    cfg: DictConfig, out_dir: Path, episodes: Sequence[Episode], records: Sequence[Mapping[str, Any]], actions: Mapping[str, list[int]]
) -> list[Path]:
    """``videos/<episode_id>.mp4`` for the recorded episodes (replayed from their actions)."""
    from findview.imageio import load_panorama
    from findview_baselines.evaluation.viz import replay_rotations, write_video

    by_id = {r["episode_id"]: r for r in records}
    pitch_bound = int(_get(cfg, "task.pitch_bound", 60))
    step_deg = int(_get(cfg, "task.step_deg", 1))
    written = []
    for ep in episodes:
        acts = actions.get(ep.episode_id)
        rec = by_id.get(ep.episode_id)
        if acts is None or rec is None:
            continue
        rots = replay_rotations((ep.init_pitch, ep.init_yaw), acts, pitch_bound, step_deg)
        if rots[-1] != (rec["final_pitch"], rec["final_yaw"]) or len(acts) != rec["steps"]:
            log.warning("episode %s: replayed trajectory does not match its record; video skipped", ep.episode_id)
            continue
        pano = load_panorama(ep.image)
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in ep.episode_id)
        path = write_video(
            out_dir / "videos" / f"{safe}.mp4", pano, rots, (ep.target_pitch, ep.target_yaw),
            float(_get(cfg, "sim.fov", 90)), int(_get(cfg, "sim.height", 256)), int(_get(cfg, "sim.width", 256)),
            str(_get(cfg, "sim.mode", "bilinear")), float(_get(cfg, "video_fps", 30)), _get(cfg, "video_pano_height"),
        )
        written.append(path)
    return written


def evaluate(
    cfg: DictConfig,
    out_dir: str | os.PathLike,
    choices: Mapping[str, str] | None = None,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """Run one evaluation and write its results into ``out_dir``; returns the summary.

    Args:
        cfg: the composed ``eval`` config.
        out_dir: the run folder.
        choices: Hydra's config-group choices (``{"agent": "sift", "dataset": "folder", ...}``).
        overrides: the command-line overrides (for the make_dataset hint and explicit agent detection).
    """
    from findview_baselines.evaluation.harness import TrajectoryRecorder, run_episodes
    from findview_baselines.evaluation.results import write_results

    choices = dict(choices or {})
    out = Path(out_dir)
    if _get(cfg, "checkpoint"):
        chosen = str(_get(cfg, "agent.name", "?"))
        if chosen != "ppo" and _overridden(overrides, "agent"):
            raise EvalError(f"checkpoint= evaluates a learned agent; it cannot be combined with agent={chosen} "
                            f"(use agent=ppo or drop agent=)")
        apply_checkpoint_config(cfg, overrides)
        choices["agent"] = "ppo"
        _rewrite_hydra_config(out, cfg)
    episodes, path, dataset_name = resolve_episodes(cfg, choices.get("dataset"), overrides)
    if not episodes:
        raise EvalError(f"{path} holds no episodes (does the split have images? see its splits.json)")
    episodes = filter_episodes(episodes, _get(cfg, "difficulty"), _get(cfg, "max_episodes"))
    if not episodes:
        raise EvalError(f"{path} holds no {_get(cfg, 'difficulty')} episodes")
    num_envs = int(_get(cfg, "num_envs", 16))
    if num_envs < 1:
        raise EvalError(f"num_envs must be >= 1, got {num_envs}")
    num_envs = min(num_envs, len(episodes))
    explicit_agent = any(o.split("=", 1)[0].lstrip("+~") == "agent" for o in overrides)
    from findview.sim import resolve_device

    try:
        device = resolve_device(str(_get(cfg, "sim.device", "auto")))
    except ValueError as err:
        raise EvalError(str(err)) from err
    agent, agent_name = build_agent(cfg, num_envs, device, explicit_agent)  # fail fast on agent errors
    env = None
    try:
        env = build_env(cfg, episodes, num_envs)
        n_video = max(0, int(_get(cfg, "video", 0)))
        recorder = TrajectoryRecorder([e.episode_id for e in episodes[:n_video]]) if n_video else None
        log.info(
            "evaluating %d episodes of %s (%s) with %s on %s, %d envs; results -> %s",
            len(episodes), dataset_name, path, agent_name, env.device, num_envs, out,
        )
        records, runtime = run_episodes(
            env, agent, progress=bool(_get(cfg, "progress", True)), callbacks=[recorder] if recorder else (),
            desc=agent_name,
        )
    finally:
        if hasattr(agent, "close"):
            agent.close()
        if env is not None:
            env.close()
    if recorder is not None:
        for p in render_videos(cfg, out, episodes, records, recorder.actions):
            log.info("video: %s", p)
    meta = {
        "dataset": dataset_name,
        "split": str(_get(cfg, "split", "?")) if not _get(cfg, "episodes") else Path(path).stem,
        "agent_config": choices.get("agent", agent_name),
        "corruption": _corruption_label(cfg),
        "severity": _get(cfg, "corruption.severity", 0) if _corruption_label(cfg) != "none" else 0,
        "difficulty": _get(cfg, "difficulty"),
        "episodes_file": str(path),
        "episodes": len(records),
        "fov": float(_get(cfg, "sim.fov", 90)),
        "view": f"{int(_get(cfg, 'sim.height', 256))}x{int(_get(cfg, 'sim.width', 256))}",
        "num_envs": num_envs,
        "seed": int(_get(cfg, "seed", 0)),
        "device": str(device),
        "checkpoint": _get(cfg, "checkpoint"),
    }
    try:
        resolved = OmegaConf.to_yaml(cfg, resolve=True)
    except Exception as err:  # an unresolvable interpolation must not lose the results
        log.warning("could not resolve the config for config_resolved.yaml: %s", err)
        resolved = None
    summary = write_results(out, records, runtime.to_dict(), agent_name, meta, resolved)
    log.info("summary: %s", out / "summary.md")
    return summary
