"""Where the environment's episodes come from: a fixed list (val/test) or an on-the-fly sampler (train).

Both sources own their resume state (``state_dict`` / ``load_state_dict``, plain values loadable with
``torch.load(weights_only=True)``). The training curriculum lives here: :class:`SampledEpisodeSource`
has a difficulty :attr:`~SampledEpisodeSource.level` and a ``mode`` (docs/TASK.md, Difficulties):

- ``unbounded`` (the paper's scheduler): level ``k`` draws the difficulty uniformly from the first ``k``
  of easy, medium, hard, so easier episodes keep appearing;
- ``bounded``: level ``k`` draws only the ``k``-th difficulty.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Mapping, Protocol, Sequence

from findview.dataset.sampler import check_level, check_mode
from findview.episode import Episode

__all__ = ["EpisodeSource", "LevelSampler", "StaticEpisodeSource", "SampledEpisodeSource"]


class EpisodeSource(Protocol):
    def next(self) -> Episode | None:
        """The next episode, or ``None`` when the source is exhausted."""

    def peek(self, n: int) -> list[Episode]:
        """Up to ``n`` upcoming episodes (for prefetching their panoramas), without consuming them."""


class LevelSampler(Protocol):
    """What :class:`SampledEpisodeSource` needs (``findview.dataset.EpisodeSampler`` is one); ``mode`` is
    only passed for ``bounded`` sources."""

    def sample_level(self, level: int, mode: str = "unbounded") -> Episode:
        """One episode of curriculum level ``level`` (1..3) in ``mode`` (``unbounded`` | ``bounded``)."""


class StaticEpisodeSource:
    """Hands out a fixed list of episodes in order, then ``None``."""

    def __init__(self, episodes: Sequence[Episode]) -> None:
        self.episodes = list(episodes)
        self.index = 0

    def __len__(self) -> int:
        return len(self.episodes)

    def next(self) -> Episode | None:
        if self.index >= len(self.episodes):
            return None
        ep = self.episodes[self.index]
        self.index += 1
        return ep

    def peek(self, n: int) -> list[Episode]:
        return self.episodes[self.index : self.index + n]

    def state_dict(self) -> dict[str, int]:
        """``{"index": next episode's position}``."""
        return {"index": self.index}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.index = int(state["index"])


class SampledEpisodeSource:
    """Endless episodes from a sampler's ``sample_level(level, mode)`` (see the module docstring).

    Args:
        sampler: e.g. ``findview.dataset.EpisodeSampler``.
        level: the starting curriculum level, 1..3.
        lookahead: how many upcoming episodes :meth:`peek` may pre-draw (so the panorama bank can
            prefetch their images).
        mode: ``unbounded`` (default, the paper) | ``bounded``.

    Setting :attr:`level` to a new value discards the pre-drawn queue, so new episodes follow the new
    level at once.
    """

    def __init__(self, sampler: LevelSampler, level: int = 1, lookahead: int = 16, mode: str = "unbounded") -> None:
        self.sampler = sampler
        self._level = check_level(level)
        self.mode = check_mode(mode)
        self.lookahead = int(lookahead)
        self._queue: deque[Episode] = deque()

    @property
    def level(self) -> int:
        """The curriculum level, 1..3 (in ``unbounded`` mode: the number of difficulties mixed)."""
        return self._level

    @level.setter
    def level(self, k: int) -> None:
        k = check_level(k)
        if k != self._level:
            self._level = k
            self._queue.clear()

    def _fill(self, n: int) -> None:
        # ``mode`` is passed only when bounded, so a sampler whose ``sample_level(level)`` knows only the
        # unbounded mixing still serves an unbounded source
        kwargs = {} if self.mode == "unbounded" else {"mode": self.mode}
        while len(self._queue) < n:
            self._queue.append(self.sampler.sample_level(self._level, **kwargs))

    def next(self) -> Episode:
        self._fill(1)
        return self._queue.popleft()

    def peek(self, n: int) -> list[Episode]:
        self._fill(min(n, self.lookahead))
        return list(self._queue)[:n]

    def state_dict(self) -> dict[str, Any]:
        """Level, mode, the pre-drawn queue and the sampler's state (if it has ``state_dict``)."""
        return {
            "level": self._level,
            "mode": self.mode,
            "queue": [e.to_dict() for e in self._queue],
            "sampler": self.sampler.state_dict() if hasattr(self.sampler, "state_dict") else None,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict`; afterwards the source hands out exactly the episodes the saved one
        would have.

        Raises:
            ValueError: the saved mode differs from this source's, or the state holds a sampler state
                that this sampler cannot load.
        """
        mode = state.get("mode", self.mode)
        if mode != self.mode:
            raise ValueError(f"the saved episode source used curriculum mode {mode!r}, this one {self.mode!r}")
        if state.get("sampler") is not None and not hasattr(self.sampler, "load_state_dict"):
            raise ValueError("the saved source state holds a sampler state but this sampler cannot load one")
        self._level = check_level(state["level"])
        self._queue = deque(Episode.from_dict(e) for e in state["queue"])
        if state.get("sampler") is not None:
            self.sampler.load_state_dict(state["sampler"])
