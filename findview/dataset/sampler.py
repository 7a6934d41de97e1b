"""Vectorised rejection sampling of FindView episodes (SPEC section 4).

:func:`sample_rotations` draws candidate (init, target) pairs in numpy batches and keeps those meeting
the difficulty rule (:mod:`findview.dataset.difficulty`); :class:`EpisodeSampler` wraps it for training
(on-the-fly episodes, random images) and the static episode files use it directly.
"""

from __future__ import annotations

import hashlib
from typing import Sequence

import numpy as np

from findview.dataset.difficulty import (
    check_difficulty,
    check_fov,
    check_hard_rule,
    check_pitch_bound,
    difficulty_mask,
    pitch_distribution,
)
from findview.dataset.discovery import ImageEntry
from findview.episode import DIFFICULTIES, Episode
from findview.geometry import yaw_diff

__all__ = ["EpisodeSampler", "SamplingError", "sample_rotations", "sample_pitch", "derive_seed", "DEFAULT_MAX_TRIES"]

DEFAULT_MAX_TRIES = 100_000


class SamplingError(RuntimeError):
    """No (init, target) pair meets the difficulty within the bounded number of tries."""


def derive_seed(*parts: object) -> int:
    """A stable 31-bit seed from ``parts`` (sha256 of their ``repr``; same on every machine)."""
    digest = hashlib.sha256(repr(tuple(parts)).encode("utf-8")).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def sample_pitch(rng: np.random.Generator, n: int, pitch_bound: int = 60) -> np.ndarray:
    """``n`` integer pitches (degrees, int64) from :func:`findview.dataset.difficulty.pitch_distribution`
    (inverse-CDF sampling)."""
    values, probs = pitch_distribution(pitch_bound)
    cdf = np.cumsum(probs)
    cdf[-1] = 1.0
    return values[np.searchsorted(cdf, rng.random(n), side="right").clip(0, len(values) - 1)]


def sample_rotations(
    difficulty: str,
    n: int,
    rng: np.random.Generator,
    fov: float,
    pitch_bound: int = 60,
    max_steps: int = 5000,
    hard_rule: str = "or",
    max_tries: int = DEFAULT_MAX_TRIES,
) -> np.ndarray:
    """Draw ``n`` (init, target) rotations meeting ``difficulty``.

    Args:
        difficulty: ``easy`` | ``medium`` | ``hard``.
        n: how many pairs.
        rng: numpy generator (the result is a deterministic function of its state).
        fov: horizontal FoV, degrees, in (0, 180).
        pitch_bound: pitches in ``[-pitch_bound, pitch_bound]`` degrees (<= 90).
        max_steps: T; every pair has ``10 < L1 < max_steps``.
        hard_rule: ``or`` | ``and``.
        max_tries: candidate budget per requested pair; if not a single candidate out of the first
            ``max_tries`` is accepted, the difficulty is deemed impossible.

    Returns:
        ``(n, 4)`` int64 array of integer degrees: ``init_pitch, init_yaw, target_pitch, target_yaw``
        (yaw in ``(-180, 180]``).

    Raises:
        SamplingError: naming the difficulty, fov, pitch bound, max_steps and hard rule.
    """
    check_difficulty(difficulty)
    fov = check_fov(fov)
    pitch_bound = check_pitch_bound(pitch_bound)
    hard_rule = check_hard_rule(hard_rule)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    out = np.empty((n, 4), dtype=np.int64)
    got = tried = 0
    budget = max_tries * max(n, 1)
    while got < n:
        if tried >= budget or (got == 0 and tried >= max_tries):
            raise SamplingError(
                f"cannot sample a {difficulty!r} episode with fov={fov:g}, pitch_bound={pitch_bound}, "
                f"max_steps={max_steps}, hard_rule={hard_rule!r}: {got} of {n} found after {tried} tries "
                f"(the difficulty is impossible or too rare under these settings)"
            )
        need = n - got
        rate = got / tried if got else 0.0
        batch = int(need / rate * 1.2) + 256 if rate > 0 else max(4096, 8 * need)
        batch = min(batch, 1 << 20, budget - tried)
        tried += batch
        pi = sample_pitch(rng, batch, pitch_bound)
        pt = sample_pitch(rng, batch, pitch_bound)
        yi = rng.integers(-179, 181, size=batch, dtype=np.int64)
        yt = rng.integers(-179, 181, size=batch, dtype=np.int64)
        keep = difficulty_mask(np.abs(pi - pt), yaw_diff(yi, yt), difficulty, fov, max_steps, hard_rule)
        idx = np.flatnonzero(keep)[:need]
        k = idx.size
        out[got : got + k, 0] = pi[idx]
        out[got : got + k, 1] = yi[idx]
        out[got : got + k, 2] = pt[idx]
        out[got : got + k, 3] = yt[idx]
        got += k
    return out


class EpisodeSampler:
    """On-the-fly episodes: a random image and a rotation pair meeting the requested difficulty.

    Args:
        images: the panoramas to draw from (uniformly); ``ImageEntry`` or plain paths (label ``""``).
        fov: horizontal FoV, degrees, in (0, 180).
        seed: the whole stream of episodes is a deterministic function of ``seed`` and the call sequence.
        pitch_bound: pitches in ``[-pitch_bound, pitch_bound]`` degrees (<= 90).
        max_steps: T (every episode has ``10 < L1 < max_steps``).
        hard_rule: ``or`` (default, the published numbers) | ``and`` (the paper's text).
        max_tries: rejection-sampling budget, see :func:`sample_rotations`.
        id_prefix: episode ids are ``f"{id_prefix}-{counter:09d}"`` (default ``f"s{seed}-fov{fov:g}"``).
        buffer: rotation pairs pre-sampled per difficulty in one vectorised batch.

    Episode ids count up from 0 in call order, so they are unique within a sampler and stable across
    runs; each episode's ``seed`` is :func:`derive_seed` of the sampler seed and the counter.
    """

    def __init__(
        self,
        images: Sequence[ImageEntry | str],
        fov: float,
        seed: int = 0,
        pitch_bound: int = 60,
        max_steps: int = 5000,
        hard_rule: str = "or",
        max_tries: int = DEFAULT_MAX_TRIES,
        id_prefix: str | None = None,
        buffer: int = 256,
    ) -> None:
        self.images = [im if isinstance(im, ImageEntry) else ImageEntry(str(im), "") for im in images]
        if not self.images:
            raise ValueError("EpisodeSampler needs at least one image")
        self.fov = check_fov(fov)
        self.seed = int(seed)
        self.pitch_bound = check_pitch_bound(pitch_bound)
        if int(max_steps) <= 11:
            raise ValueError(f"max_steps must be > 11 (episodes need 10 < L1 < max_steps), got {max_steps}")
        self.max_steps = int(max_steps)
        self.hard_rule = check_hard_rule(hard_rule)
        self.max_tries = int(max_tries)
        self.id_prefix = id_prefix if id_prefix is not None else f"s{self.seed}-fov{self.fov:g}"
        self.buffer = max(1, int(buffer))
        root = np.random.SeedSequence([self.seed, 0x46564453])  # "FVDS"
        children = root.spawn(1 + len(DIFFICULTIES))
        self._rng = np.random.default_rng(children[0])
        self._rot_rng = {d: np.random.default_rng(c) for d, c in zip(DIFFICULTIES, children[1:])}
        self._pool: dict[str, np.ndarray] = {d: np.empty((0, 4), np.int64) for d in DIFFICULTIES}
        self._pos: dict[str, int] = {d: 0 for d in DIFFICULTIES}
        self.count = 0

    def _next_rotation(self, difficulty: str) -> np.ndarray:
        if self._pos[difficulty] >= len(self._pool[difficulty]):
            self._pool[difficulty] = sample_rotations(
                difficulty, self.buffer, self._rot_rng[difficulty], self.fov, self.pitch_bound,
                self.max_steps, self.hard_rule, self.max_tries,
            )
            self._pos[difficulty] = 0
        row = self._pool[difficulty][self._pos[difficulty]]
        self._pos[difficulty] += 1
        return row

    def sample(self, difficulty: str) -> Episode:
        """One episode of ``difficulty`` (``easy`` | ``medium`` | ``hard``) on a uniformly drawn image."""
        check_difficulty(difficulty)
        rot = self._next_rotation(difficulty)
        image = self.images[int(self._rng.integers(len(self.images)))]
        k = self.count
        self.count += 1
        return Episode(
            episode_id=f"{self.id_prefix}-{k:09d}",
            image=image.path,
            init_pitch=int(rot[0]),
            init_yaw=int(rot[1]),
            target_pitch=int(rot[2]),
            target_yaw=int(rot[3]),
            difficulty=difficulty,
            label=image.label,
            seed=derive_seed("sampler", self.seed, k),
        )

    def sample_level(self, level: int) -> Episode:
        """One episode whose difficulty is uniform over the first ``level`` (1..3) of easy, medium, hard."""
        if isinstance(level, bool) or int(level) != level or not 1 <= int(level) <= len(DIFFICULTIES):
            raise ValueError(f"level must be an integer in [1, {len(DIFFICULTIES)}], got {level!r}")
        return self.sample(DIFFICULTIES[int(self._rng.integers(int(level)))])
