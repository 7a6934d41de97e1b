"""Where the environment's episodes come from: a fixed list (val/test) or an on-the-fly sampler (train)."""

from __future__ import annotations

from collections import deque
from typing import Protocol, Sequence

from findview.episode import Episode


class EpisodeSource(Protocol):
    def next(self) -> Episode | None:
        """The next episode, or ``None`` when the source is exhausted."""

    def peek(self, n: int) -> list[Episode]:
        """Up to ``n`` upcoming episodes (for prefetching their panoramas), without consuming them."""


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

    def state_dict(self) -> dict:
        return {"index": self.index}

    def load_state_dict(self, state: dict) -> None:
        self.index = int(state["index"])


class SampledEpisodeSource:
    """Endless episodes from a sampler with ``sample_level(k) -> Episode`` (difficulty level ``k``).

    A short queue of pre-drawn episodes lets the panorama bank prefetch their images. Changing
    :attr:`level` discards the queue so new episodes follow the new level at once.
    """

    def __init__(self, sampler, level: int = 1, lookahead: int = 16) -> None:
        self.sampler = sampler
        self._level = int(level)
        self.lookahead = int(lookahead)
        self._queue: deque[Episode] = deque()

    @property
    def level(self) -> int:
        return self._level

    @level.setter
    def level(self, k: int) -> None:
        if int(k) != self._level:
            self._level = int(k)
            self._queue.clear()

    def _fill(self, n: int) -> None:
        while len(self._queue) < n:
            self._queue.append(self.sampler.sample_level(self._level))

    def next(self) -> Episode:
        self._fill(1)
        return self._queue.popleft()

    def peek(self, n: int) -> list[Episode]:
        self._fill(min(n, self.lookahead))
        return list(self._queue)[:n]

    def state_dict(self) -> dict:
        """Level, queued episodes and the sampler's RNG state (if it has ``state_dict``)."""
        return {
            "level": self._level,
            "queue": [e.to_dict() for e in self._queue],
            "sampler": self.sampler.state_dict() if hasattr(self.sampler, "state_dict") else None,
        }

    def load_state_dict(self, state: dict) -> None:
        self._level = int(state["level"])
        self._queue = deque(Episode.from_dict(e) for e in state["queue"])
        if state.get("sampler") is not None:
            if not hasattr(self.sampler, "load_state_dict"):
                raise ValueError("saved source state has a sampler state but this sampler cannot load one")
            self.sampler.load_state_dict(state["sampler"])
