"""Per-episode corruption of the target image (docs/TASK.md, section Corruptions).

:class:`EpisodeCorruption` is the environment's ``target_transform`` for ``corruption.name != none``:
once per episode, when the episode starts, the rendered target view is corrupted with a corruption and a
severity drawn from the episode's own seed, so every agent (rule-based or learned), every ``num_envs``
and every rerun sees the very same corrupted target for the same episode. The current view stays clean.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from findview.episode import Episode

__all__ = ["EpisodeCorruption"]

#: mixed into the episode seed so the corruption's random stream differs from the episode sampler's
_STREAM = 0x5EC0


class EpisodeCorruption:
    """Corrupt each episode's target once, reproducibly from ``episode.seed``.

    Args:
        names: corruption names to draw from (per episode; uniformly unless ``weights`` says otherwise).
        low, high: severity range (inclusive, 1-5), drawn uniformly per episode.
        clean_fraction: share of episodes (drawn per episode, from its seed) whose target stays clean; 0 draws
            exactly as before the option existed.
        weights: relative draw weight of each name (a mapping; names it leaves out weigh 1), e.g. ``{"fog": 3}``
            draws fog three times as often as any other name; ``None`` (or an empty mapping) draws uniformly,
            exactly as before the option existed.

    Attributes:
        max_severity: the current upper bound of the drawn severity (``<= high``); the trainer raises it
            from ``low`` to ``high`` when ``corruption.ramp_updates > 0``.
    """

    def __init__(
        self, names: Sequence[str], low: int, high: int, clean_fraction: float = 0.0,
        weights: Mapping[str, float] | None = None,
    ) -> None:
        if not names:
            raise ValueError("EpisodeCorruption needs at least one corruption name")
        if not 1 <= int(low) <= int(high) <= 5:
            raise ValueError(f"corruption.severity range [{low}, {high}]: expected 1 <= low <= high <= 5")
        self.names = tuple(names)
        if not 0.0 <= float(clean_fraction) < 1.0:
            raise ValueError(f"corruption.clean_fraction={clean_fraction}: expected a share in [0, 1)")
        self.low, self.high = int(low), int(high)
        self.clean_fraction = float(clean_fraction)
        self.max_severity = self.high
        self.cumulative: np.ndarray | None = None  # cumulative draw probabilities when weighted
        if weights:
            unknown = sorted(set(weights) - set(self.names))
            if unknown:
                raise ValueError(f"corruption.weights names {unknown}, which are not drawn here; expected some of {self.names}")
            w = np.array([float(weights.get(n, 1.0)) for n in self.names])
            if not (np.isfinite(w).all() and (w >= 0).all() and w.sum() > 0):
                raise ValueError(f"corruption.weights={dict(weights)}: expected weights >= 0, not all 0")
            self.cumulative = np.cumsum(w / w.sum())

    def choice(self, episode: Episode) -> tuple[str, int]:
        """The ``(name, severity)`` this episode's target gets (a function of its seed and ``max_severity``);
        ``("none", 0)`` for a clean one (``clean_fraction``)."""
        if self.clean_fraction > 0.0:  # its own stream, so the draws below stay those of clean_fraction = 0
            if np.random.default_rng([int(episode.seed) % 2**63, _STREAM, 1]).random() < self.clean_fraction:
                return "none", 0
        rng = np.random.default_rng([int(episode.seed) % 2**63, _STREAM])
        if self.cumulative is None:
            name = self.names[int(rng.integers(len(self.names)))]
        else:
            index = int(np.searchsorted(self.cumulative, rng.random(), side="right"))
            name = self.names[min(index, len(self.names) - 1)]
        severity = int(rng.integers(self.low, max(self.low, self.max_severity) + 1))
        return name, severity

    def info(self, episode: Episode) -> dict[str, object]:
        """``{"corruption": name, "severity": s}`` for the episode's record."""
        name, severity = self.choice(episode)
        return {"corruption": name, "severity": severity}

    def __call__(self, target: torch.Tensor, episode: Episode) -> torch.Tensor:
        """Corrupt one target view ``(3, H, W)`` uint8; returns ``(3, H, W)`` uint8 on the same device."""
        from findview.corruptions import corrupt

        name, severity = self.choice(episode)
        if name == "none":
            return target
        generator = torch.Generator().manual_seed((int(episode.seed) * 1_000_003 + _STREAM) % 2**63)
        return corrupt(target.unsqueeze(0), name, severity, generator=generator)[0]
