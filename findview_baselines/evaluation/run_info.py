"""What names and describes one evaluation run: the title its agent is shown under (a learned agent by
the trainer and variant stored in its checkpoint), its settings that differ from the defaults (from the
run folder's Hydra record), and the flattened, comparable form of a config. Used by the result files of
one run (``results.py``) and by the multirun tables (``collect.py``)."""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["learned_agent_info", "agent_title", "non_default_settings", "run_settings"]


def learned_agent_info(checkpoint: Any) -> dict[str, str]:
    """``{"trainer": "dagger", "variant": "direct"}`` of a learned agent's checkpoint (from the run config
    it stores); ``{}`` for what cannot be read (a missing or foreign file: the tools report that)."""
    path = Path(os.path.expanduser(str(checkpoint)))
    try:
        stamp = path.stat().st_mtime_ns
    except OSError:
        return {}
    return dict(_checkpoint_info(str(path), stamp))


@functools.lru_cache(maxsize=64)
def _checkpoint_info(path: str, _stamp: int) -> tuple[tuple[str, str], ...]:
    from findview_baselines.rl.checkpoint import load_checkpoint

    try:
        state = load_checkpoint(path)
    except (OSError, ValueError):
        return ()
    conf = state.get("config") if isinstance(state, Mapping) else None
    conf = conf if isinstance(conf, Mapping) else {}
    trainer = conf.get("trainer") if isinstance(conf.get("trainer"), Mapping) else {}
    sig = state.get("signature") if isinstance(state.get("signature"), Mapping) else {}
    info = {"trainer": trainer.get("algorithm"), "variant": sig.get("variant")}
    return tuple((k, str(v)) for k, v in info.items() if v not in (None, ""))


def agent_title(agent: str, meta: Mapping[str, Any]) -> str:
    """The name a run's agent is shown under: a learned agent (``ppo`` config, a ``checkpoint``) by the
    algorithm that trained it and its network variant (``dagger direct``; ``learned`` when the checkpoint
    does not say), a rule-based agent by its name."""
    if agent != "ppo" or not meta.get("checkpoint"):
        return agent
    trainer, variant = meta.get("trainer"), meta.get("variant")
    return " ".join(str(x) for x in (trainer or "learned", variant) if x)


def non_default_settings(
    config: Mapping[str, Any], defaults: Mapping[str, Any], choices: Mapping[str, str] | None = None
) -> list[str]:
    """``key=value`` for every leaf of ``config`` that differs from (or is missing in) ``defaults``, in
    key order, after the config-group choices that differ from the primary config's (``sim=fov60``)."""
    out = [f"{g}={c}" for g, c in sorted((choices or {}).items())]
    flat, base = _flatten(config), _flatten(defaults)
    out += [f"{k}={v}" for k, v in sorted(flat.items()) if not k.startswith("hydra.") and base.get(k) != v]
    return out


def _hydra_choices(run_dir: Path) -> tuple[str, dict[str, str]] | None:
    """``(config name, config-group choices)`` of a run, from its ``.hydra/hydra.yaml``."""
    path = run_dir / ".hydra" / "hydra.yaml"
    if not path.is_file():
        return None
    from omegaconf import OmegaConf

    hydra_cfg = OmegaConf.load(path).hydra
    choices = {str(k): str(v) for k, v in hydra_cfg.runtime.choices.items()
               if not str(k).startswith("hydra/") and v is not None}
    return str(hydra_cfg.job.config_name), choices


def _compose_any(config_name: str, overrides: list[str], return_hydra_config: bool = False) -> Any:
    """Compose a tool's config, inside a running tool (and its joblib workers) or outside one."""
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        from hydra import compose

        return compose(config_name, overrides=overrides, return_hydra_config=return_hydra_config)
    from findview_baselines.config import compose_config

    return compose_config(config_name, overrides, return_hydra_config=return_hydra_config)


def _compose(config_name: str, overrides: list[str]) -> dict[str, Any]:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(_compose_any(config_name, overrides), resolve=True)  # type: ignore[return-value]


def run_settings(run_dir: str | os.PathLike, resolved_config: str) -> list[str] | None:
    """The settings of the run in ``run_dir`` that differ from the defaults: its config (the resolved YAML
    text) against the tool's config composed with the same config-group choices (a learned agent:
    ``agent=ppo``), plus the group choices that differ from the tool's defaults. ``None`` when the run
    folder has no Hydra record or the defaults cannot be composed (the results are written anyway)."""
    from omegaconf import OmegaConf

    found = _hydra_choices(Path(run_dir))
    if found is None:
        return None
    config_name, choices = found
    config = OmegaConf.to_container(OmegaConf.create(resolved_config), resolve=True)
    if not isinstance(config, dict):
        return None
    agent = config.get("agent") if isinstance(config.get("agent"), Mapping) else {}
    if config.get("checkpoint") and agent.get("name") == "ppo":
        choices["agent"] = "ppo"  # a checkpoint implies the learned agent, whatever the default group is
    groups = [g for g in choices if "/" not in g and g != "experiment"]
    try:
        defaults = _compose(config_name, [f"{g}={choices[g]}" for g in groups])
        base_choices = _hydra_default_choices(config_name)
    except Exception:  # a group option that no longer exists, ...: the settings line is left out
        return None
    changed = {g: choices[g] for g in groups if base_choices.get(g) != choices[g]}
    if choices.get("experiment"):
        changed["+experiment"] = choices["experiment"]
    return non_default_settings(config, defaults, changed)


def _hydra_default_choices(config_name: str) -> dict[str, str]:
    cfg = _compose_any(config_name, [], return_hydra_config=True)
    return {str(k): str(v) for k, v in cfg.hydra.runtime.choices.items() if v is not None}


def _canon(value: Any) -> str:
    """A comparable string for a config value (``inf`` for infinities, ``true`` / ``false``, JSON for lists
    / mappings)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "inf" if value == math.inf else ("-inf" if value == -math.inf else repr(value))
    if isinstance(value, (list, tuple, Mapping)):
        return json.dumps(value, sort_keys=True, default=str)
    return "null" if value is None else str(value)


def _flatten(cfg: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in cfg.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping) and v:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = _canon(v)
    return out
