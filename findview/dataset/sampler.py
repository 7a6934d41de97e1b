"""Vectorised rejection sampling of FindView episodes (docs/TASK.md, Difficulties).

:func:`sample_rotations` draws candidate (init, target) pairs in numpy batches and keeps those meeting
the difficulty rule (:mod:`findview.dataset.difficulty`); :class:`EpisodeSampler` wraps it for training
(on-the-fly episodes, random images, the curriculum's difficulty levels, an exactly resumable state)
and the static episode files use it directly.
"""

from __future__ import annotations

import copy
import hashlib
from typing import Any, Mapping, Sequence

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

__all__ = [
    "EpisodeSampler",
    "SamplingError",
    "sample_rotations",
    "sample_pitch",
    "derive_seed",
    "check_level",
    "check_mode",
    "DEFAULT_MAX_TRIES",
    "LEVEL_MODES",
]

DEFAULT_MAX_TRIES = 100_000
LEVEL_MODES = ("unbounded", "bounded")
"""Curriculum modes: ``unbounded`` level ``k`` is uniform over the first ``k`` difficulties (the paper's
scheduler, easier episodes keep appearing); ``bounded`` level ``k`` is only the ``k``-th difficulty."""
_STATE_VERSION = 1


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


def check_level(level: int) -> int:
    """Return ``level`` as int or raise ``ValueError`` unless it is an integer in ``[1, 3]``."""
    try:
        ok = not isinstance(level, bool) and int(level) == level and 1 <= int(level) <= len(DIFFICULTIES)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"level must be an integer in [1, {len(DIFFICULTIES)}], got {level!r}")
    return int(level)


def check_mode(mode: str) -> str:
    """Return ``mode`` or raise ``ValueError`` unless it is one of :data:`LEVEL_MODES`."""
    if mode not in LEVEL_MODES:
        raise ValueError(f"unknown curriculum mode {mode!r}; valid: {', '.join(LEVEL_MODES)}")
    return mode


def _plain(obj: Any) -> Any:
    """``obj`` with numpy scalars / arrays turned into Python ints, floats and lists (for ``torch.save``
    files loaded with ``weights_only=True`` and for JSON)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


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

    :meth:`state_dict` / :meth:`load_state_dict` save and restore everything the stream depends on, so a
    sampler restored from a state continues with exactly the episodes the saved one would have drawn.
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

    def sample_level(self, level: int, mode: str = "unbounded") -> Episode:
        """One episode of curriculum level ``level`` (1..3).

        Args:
            level: 1 = easy, 2 = medium, 3 = hard (docs/TASK.md, Difficulties).
            mode: ``unbounded``: the difficulty is uniform over the first ``level`` of easy, medium, hard
                (one draw from the sampler's generator); ``bounded``: exactly the ``level``-th difficulty.
        """
        level = check_level(level)
        if check_mode(mode) == "bounded":
            return self.sample(DIFFICULTIES[level - 1])
        return self.sample(DIFFICULTIES[int(self._rng.integers(level))])

    # ---------------------------------------------------------------------------------------------
    def _settings(self) -> dict[str, Any]:
        return {
            "seed": self.seed, "fov": self.fov, "pitch_bound": self.pitch_bound, "max_steps": self.max_steps,
            "hard_rule": self.hard_rule, "num_images": len(self.images), "id_prefix": self.id_prefix,
        }

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the stream exactly: the generators' states, the pre-sampled
        rotation pools, their read positions, the episode counter, and the settings (checked on load).

        Plain Python values only (ints, floats, strings, lists, dicts): loadable with
        ``torch.load(weights_only=True)`` and JSON-serialisable.
        """
        return {
            "version": _STATE_VERSION,
            "settings": self._settings(),
            "count": int(self.count),
            "rng": _plain(copy.deepcopy(self._rng.bit_generator.state)),
            "rot_rng": {d: _plain(copy.deepcopy(g.bit_generator.state)) for d, g in self._rot_rng.items()},
            "pool": {d: _plain(np.asarray(p, dtype=np.int64)) for d, p in self._pool.items()},
            "pos": {d: int(p) for d, p in self._pos.items()},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict` (of a sampler with the same settings).

        Raises:
            ValueError: the state is not a sampler state of this version, or was saved by a sampler with
                other settings (seed, FoV, pitch bound, max steps, hard rule, number of images, id prefix);
                the message names the first differing setting.
        """
        if not isinstance(state, Mapping) or state.get("version") != _STATE_VERSION or "rng" not in state:
            raise ValueError(f"not an EpisodeSampler state (version {_STATE_VERSION}): keys {sorted(state)[:8]}"
                             if isinstance(state, Mapping) else f"not an EpisodeSampler state: {type(state).__name__}")
        mine = self._settings()
        for key, value in dict(state.get("settings", {})).items():
            if key in mine and mine[key] != value:
                raise ValueError(
                    f"the saved episode sampler state was made with {key}={value!r} but this sampler has "
                    f"{key}={mine[key]!r}; it cannot continue that stream"
                )
        self._rng.bit_generator.state = copy.deepcopy(dict(state["rng"]))
        for d in DIFFICULTIES:
            self._rot_rng[d].bit_generator.state = copy.deepcopy(dict(state["rot_rng"][d]))
            pool = np.asarray(state["pool"][d], dtype=np.int64)
            self._pool[d] = pool.reshape(-1, 4) if pool.size else np.empty((0, 4), np.int64)
            self._pos[d] = int(state["pos"][d])
        self.count = int(state["count"])
