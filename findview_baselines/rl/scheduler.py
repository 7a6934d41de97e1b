"""Difficulty scheduler (paper section 4.4; docs/TASK.md, sections Difficulties and PPO baseline).

Training is split into ``num_levels`` equal phases of updates; phase ``k`` (1-based) is level ``k``:

- ``unbounded`` (paper): level ``k`` samples episodes uniformly from the first ``k`` difficulties
  (easy; easy + medium; easy + medium + hard), so easier episodes keep appearing.
- ``bounded``: level ``k`` samples only the ``k``-th difficulty.

With ``total_updates = 30000`` and 3 levels: updates 0..9999 -> 1, 10000..19999 -> 2, 20000.. -> 3.
"""

from __future__ import annotations

from typing import Any, Mapping

from findview.episode import DIFFICULTIES

MODES = ("unbounded", "bounded")


class DifficultyScheduler:
    """Maps an update index to a difficulty level and to the difficulties to sample from."""

    def __init__(self, total_updates: int, num_levels: int = 3, mode: str = "unbounded") -> None:
        if total_updates <= 0:
            raise ValueError(f"total_updates must be positive, got {total_updates}")
        if not 1 <= num_levels <= len(DIFFICULTIES):
            raise ValueError(f"num_levels must be in [1, {len(DIFFICULTIES)}], got {num_levels}")
        if mode not in MODES:
            raise ValueError(f"unknown scheduler mode {mode!r}; choose one of {MODES}")
        self.total_updates = int(total_updates)
        self.num_levels = int(num_levels)
        self.mode = mode
        self.current_level = 1

    def level(self, update: int) -> int:
        """Level (1..num_levels) for update ``update`` (0-based); updates past the end stay at the top level."""
        phase = max(0, update) * self.num_levels // self.total_updates
        return 1 + min(self.num_levels - 1, phase)

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
            "current_level": self.current_level,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a saved schedule (its total / levels / mode win over the constructor's, so a resumed run
        levels up at the same updates as the original)."""
        self.total_updates = int(state["total_updates"])
        self.num_levels = int(state["num_levels"])
        self.mode = str(state["mode"])
        self.current_level = int(state["current_level"])
