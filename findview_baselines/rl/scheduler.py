"""Difficulty scheduler (paper section 4.4; docs/TASK.md, sections Difficulties and PPO baseline).

Training is split into ``num_levels`` equal phases of updates; phase ``k`` (1-based) is level ``k``:

- ``unbounded`` (paper): level ``k`` samples episodes uniformly from the first ``k`` difficulties
  (easy; easy + medium; easy + medium + hard), so easier episodes keep appearing.
- ``bounded``: level ``k`` samples only the ``k``-th difficulty.

With ``total_updates = 30000`` and 3 levels: updates 0..9999 -> 1, 10000..19999 -> 2, 20000.. -> 3.

``start_level = s > 1`` starts the curriculum at level ``s`` (a fine-tuning run from ``init_from`` need not
go back to easy episodes): the updates are split into ``num_levels - s + 1`` phases, levels ``s .. num_levels``.
With 3 levels and ``s = 3`` every update is at level 3.
"""

from __future__ import annotations

from typing import Any, Mapping

from findview.episode import DIFFICULTIES

MODES = ("unbounded", "bounded")


class DifficultyScheduler:
    """Maps an update index to a difficulty level and to the difficulties to sample from."""

    def __init__(self, total_updates: int, num_levels: int = 3, mode: str = "unbounded", start_level: int = 1) -> None:
        if total_updates <= 0:
            raise ValueError(f"total_updates must be positive, got {total_updates}")
        if not 1 <= num_levels <= len(DIFFICULTIES):
            raise ValueError(f"num_levels must be in [1, {len(DIFFICULTIES)}], got {num_levels}")
        if mode not in MODES:
            raise ValueError(f"unknown scheduler mode {mode!r}; choose one of {MODES}")
        if not 1 <= start_level <= num_levels:
            raise ValueError(f"start_level must be in [1, num_levels={num_levels}], got {start_level}")
        self.total_updates = int(total_updates)
        self.num_levels = int(num_levels)
        self.mode = mode
        self.start_level = int(start_level)
        self.current_level = self.start_level

    def level(self, update: int) -> int:
        """Level (start_level..num_levels) for update ``update`` (0-based); updates past the end stay at the
        top level."""
        phases = self.num_levels - self.start_level + 1
        phase = max(0, update) * phases // self.total_updates
        return self.start_level + min(phases - 1, phase)

    def difficulties(self, level: int) -> tuple[str, ...]:
        """Difficulty names sampled (uniformly) at ``level``."""
        if self.mode == "unbounded":
            return DIFFICULTIES[:level]
        return (DIFFICULTIES[level - 1],)

    def step(self, update: int) -> bool:
        """Move to the level of ``update``; returns True when the level changed (the trainer then updates the
        episode source, e.g. ``SampledEpisodeSource.level``)."""
        new_level = self.level(update)
        changed = new_level != self.current_level
        self.current_level = new_level
        return changed

    # ---------------------------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "total_updates": self.total_updates,
            "num_levels": self.num_levels,
            "mode": self.mode,
            "start_level": self.start_level,
            "current_level": self.current_level,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a saved schedule (its total / levels / mode win over the constructor's, so a resumed run
        levels up at the same updates as the original)."""
        self.total_updates = int(state["total_updates"])
        self.num_levels = int(state["num_levels"])
        self.mode = str(state["mode"])
        self.start_level = int(state.get("start_level", 1))  # saved before start_level existed: 1
        self.current_level = int(state["current_level"])
