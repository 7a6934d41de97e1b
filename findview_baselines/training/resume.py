"""Resuming a training run from ``checkpoints/latest.pth``: reading it (:func:`read_resume_state`), this
rank's part of the trainer state (:func:`rank_trainer_state`, also with another number of ranks than saved)
and the warning about config values that changed since."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import torch

from findview_baselines.errors import UserError
from findview_baselines.rl import distributed
from findview_baselines.rl.checkpoint import load_checkpoint

log = logging.getLogger(__name__)

__all__ = ["RANK_DATA_KEYS", "read_resume_state", "rank_trainer_state", "warn_config_changes"]

#: per-rank entries bound to a rank's environments and data; dropped when resuming with another rank count
RANK_DATA_KEYS = ("env", "storage", "current", "episode_returns", "buffer", "rng")
#: config keys that may change between sessions without a warning
SESSION_KEYS = ("resume", "progress", "stop_after")


def warn_config_changes(saved: Mapping[str, Any], current: Mapping[str, Any], prefix: str = "") -> None:
    """Log the config values that differ between a checkpoint and the current run (resume keeps going)."""
    for key in sorted(set(saved) | set(current)):
        a, b = saved.get(key), current.get(key)  # two plain dicts of config values, either may lack a key
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            warn_config_changes(a, b, f"{prefix}{key}.")
        elif a != b and key not in SESSION_KEYS:
            log.warning("resuming with a changed config value %s%s: %r -> %r", prefix, key, a, b)


def read_resume_state(latest: Path, resume: bool, config: Mapping[str, Any]) -> dict[str, Any] | None:
    """``latest.pth`` when ``trainer.resume`` and it exists (every rank must see the same one), else ``None``.

    Raises:
        UserError: an unreadable file, one without trainer state, or ranks that see different files.
    """
    state: dict[str, Any] | None = None
    main = distributed.is_main()
    if resume and latest.is_file():
        try:
            state = load_checkpoint(latest)
        except ValueError as err:
            raise UserError(f"{err}; move it away or start over with trainer.resume=false") from None
        if state["trainer"] is None:
            raise UserError(f"{latest} holds no trainer state; start over with trainer.resume=false")
        if main:
            warn_config_changes(state["config"] or {}, config)
    elif latest.is_file() and main:
        log.warning("trainer.resume=false: starting over in %s (the old latest.pth will be overwritten)",
                    latest.parent.parent)
    if distributed.world_size() > 1:
        seen = distributed.all_gather(None if state is None else int(state["update"]))
        if len(set(seen)) > 1:
            raise UserError(f"the ranks see different resume states in {latest} (updates {seen} by rank): the "
                            f"run folder must be on a file system every machine shares")
    return state


def rank_trainer_state(trainer: Mapping[str, Any], rank: int, world: int, seed: int) -> tuple[dict[str, Any], bool]:
    """This rank's trainer state from ``latest.pth``'s ``trainer`` entry, and whether it continues exactly.

    Same number of ranks as saved: rank 0's state with rank ``rank``'s own entries on top (exact). Another
    number: rank 0's state without the environment-bound entries (:data:`RANK_DATA_KEYS`) and with every
    generator state (``*_rng``) re-seeded from :func:`distributed.reseed`; the caller restarts the
    environments."""
    saved_world = int(trainer.get("world_size", 1))  # absent in single-process checkpoints
    state = {k: v for k, v in trainer.items() if k not in ("world_size", "rank_states")}
    if saved_world == world:
        if rank > 0:
            state.update(trainer["rank_states"][rank - 1])
        return state, True
    update = int(trainer["update"])
    for key in RANK_DATA_KEYS:
        state[key] = None
    generators = sorted(key for key in state if key.endswith("_rng"))
    for i, key in enumerate(generators):
        state[key] = torch.Generator().manual_seed(distributed.reseed(seed, rank, update) + i + 1).get_state()
    return state, False
