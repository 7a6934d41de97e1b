"""What the feature-based agents (``orb``, ``sift``, ``rotation``) share: keypoints and matching,
per-slot state, lazily computed target features, the worker threads.

An agent built on :class:`FeatureAgent` only supplies its decision rule:

- :meth:`FeatureAgent.new_slot` -- the state of a slot at the start of an episode (a :class:`Slot`
  subclass; ``slot.target`` is ``None`` until the first observation);
- :meth:`FeatureAgent.prepare_target` -- what the agent keeps of the target image (computed once per
  episode, in a worker thread, on the first ``act`` that looks at the slot);
- :meth:`FeatureAgent.wants_view` -- whether the slot looks at its current view this step (default:
  always; the ``rotation`` agent skips most steps of a planned walk);
- :meth:`FeatureAgent.step` -- the action of one slot, given its view or ``None`` when it did not ask.

The base class does the rest: one host copy of the views and targets per ``act`` (no torch op runs on
the host, so a busy CPU cannot make the agent wait on idle OpenMP threads), slots processed in parallel
by ``threads`` worker threads (OpenCV releases the GIL) with ``cv2_threads`` OpenCV threads,
finished slots answering STOP without work until they are reset.

Images handed to the rule are ``(3, H, W)`` uint8 RGB numpy arrays (views of the observation on CPU);
:func:`~findview_baselines.agents.base.gray_of` turns one into the ``(H, W)`` gray image the detectors
use.
"""

from __future__ import annotations

import contextlib
import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
import torch

from findview.episode import Episode
from findview.runtime import light_work
from findview_baselines.agents.base import STOP, Agent, check_keys, episode_rng, host_images, to_plain_dict

__all__ = [
    "DETECTORS",
    "Features",
    "ViewCache",
    "detect",
    "norm_type",
    "knn2",
    "match_features",
    "ParallelRunner",
    "cv2_num_threads",
    "Slot",
    "FeatureAgent",
]

DETECTORS = ("orb", "sift")
_T = TypeVar("_T")
_R = TypeVar("_R")


# --------------------------------------------------------------------------------------------------
# features and matching
# --------------------------------------------------------------------------------------------------
@dataclass
class Features:
    """Keypoints of one image.

    Attributes:
        pts: ``(K, 2)`` float32 keypoint positions ``(x, y)`` in pixels (x = column to the right,
            y = row downwards; OpenCV convention, pixel centres at integer coordinates).
        des: ``(K, 32)`` uint8 (ORB) or ``(K, 128)`` float32 (SIFT) descriptors; ``None`` when ``K == 0``.
    """

    pts: np.ndarray
    des: np.ndarray | None

    def __len__(self) -> int:
        return int(self.pts.shape[0])


_local = threading.local()


def _detector(kind: str, n_features: int) -> cv2.Feature2D:
    """A per-thread cached OpenCV detector (Feature2D objects are not shared between threads)."""
    cache = getattr(_local, "detectors", None)
    if cache is None:
        cache = _local.detectors = {}
    key = (kind, int(n_features))
    det = cache.get(key)
    if det is None:
        if kind == "orb":
            det = cv2.ORB_create(nfeatures=int(n_features))
        elif kind == "sift":
            det = cv2.SIFT_create(nfeatures=int(n_features))
        else:
            raise ValueError(f"unknown detector {kind!r}; expected one of {DETECTORS}")
        cache[key] = det
    return det


def norm_type(kind: str) -> int:
    """OpenCV norm of the descriptors of ``kind``: Hamming for ORB, L2 for SIFT."""
    if kind == "orb":
        return cv2.NORM_HAMMING
    if kind == "sift":
        return cv2.NORM_L2
    raise ValueError(f"unknown detector {kind!r}; expected one of {DETECTORS}")


def detect(kind: str, gray: np.ndarray, n_features: int = 500) -> Features:
    """Detect keypoints and compute descriptors on a ``(H, W)`` uint8 gray image."""
    kps, des = _detector(kind, n_features).detectAndCompute(gray, None)
    if not kps or des is None:
        return Features(np.zeros((0, 2), np.float32), None)
    pts = np.array([kp.pt for kp in kps], dtype=np.float32).reshape(-1, 2)
    return Features(pts, des)


class ViewCache:
    """What a slot computed from each view it has seen (the feature rule: its vote), by the view's shape,
    dtype and bytes; the least recently used view is dropped beyond ``capacity``. An episode that runs in
    circles (the paper's rule repeats its last move when nothing matches) sees the same views again every
    360 moves. Detection and matching are the costly part of a step and depend on nothing but the view
    once the episode's target is fixed, so a hit gives exactly what computing would, for the cost of a hash.

    Args:
        capacity: views kept (0: the cache is off).
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self._items: OrderedDict[bytes, Any] = OrderedDict()
        self.hits = 0

    def __len__(self) -> int:
        return len(self._items)

    def get(self, view: np.ndarray, compute: Callable[[], _R]) -> _R:
        """The value for ``view``: cached, else ``compute()`` (stored)."""
        if self.capacity <= 0:
            return compute()
        h = hashlib.blake2b(f"{view.shape}{view.dtype.str}".encode(), digest_size=16)
        h.update(np.ascontiguousarray(view).data)
        key = h.digest()
        if key in self._items:
            self._items.move_to_end(key)
            self.hits += 1
            return self._items[key]
        value = compute()
        self._items[key] = value
        if len(self._items) > self.capacity:
            self._items.popitem(last=False)
        return value


def knn2(des_query: np.ndarray, des_train: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force 2 nearest neighbours of each query descriptor among the train descriptors.

    ORB (Hamming): ``cv2.batchDistance``, the kernel behind ``cv2.BFMatcher.knnMatch`` (same distances,
    same neighbours), without building ``DMatch`` objects. SIFT (L2): the exhaustive distance matrix
    ``|q|^2 + |t|^2 - 2 q.t`` as one float32 numpy matrix product (3-4x faster than OpenCV's loop;
    distances agree with ``BFMatcher`` to ~1e-4 relative, so only exact ties may differ, and a tie
    never passes the ratio test). numpy, not torch: no OpenMP thread pool to wait on under CPU load.

    Returns:
        ``dist (Q, 2)`` float32 descriptor distances (Hamming bit count or L2 norm), ascending, and
        ``idx (Q, 2)`` int32 train indices; with a single train descriptor the second column is
        ``inf`` / ``-1``.
    """
    q = len(des_query)
    if q == 0 or len(des_train) == 0:
        return np.zeros((q, 2), np.float32) + np.inf, np.full((q, 2), -1, np.int32)
    k = min(2, len(des_train))
    if kind == "sift":
        a = np.ascontiguousarray(des_query, dtype=np.float32)
        b = np.ascontiguousarray(des_train, dtype=np.float32)
        d2 = (a * a).sum(1, keepdims=True) + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T)
        if k == 1:
            idx = np.argmin(d2, axis=1)[:, None]
        else:  # the two smallest per row, ascending (ties: lower index first)
            idx = np.argpartition(d2, 1, axis=1)[:, :2]
            v = np.take_along_axis(d2, idx, 1)
            swap = (v[:, 1] < v[:, 0]) | ((v[:, 1] == v[:, 0]) & (idx[:, 1] < idx[:, 0]))
            idx[swap] = idx[swap][:, ::-1]
        dist = np.sqrt(np.maximum(np.take_along_axis(d2, idx, 1), 0.0)).astype(np.float32)
        idx = idx.astype(np.int32)
    else:
        dist, idx = cv2.batchDistance(des_query, des_train, -1, normType=norm_type(kind), K=k)
        dist = dist.astype(np.float32, copy=False)
    if k == 1:
        dist = np.concatenate([dist, np.full((q, 1), np.inf, np.float32)], axis=1)
        idx = np.concatenate([idx, np.full((q, 1), -1, np.int32)], axis=1)
    return dist, idx


def match_features(
    cur: Features, tgt: Features, kind: str, ratio: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2-NN matching with Lowe's ratio test.

    Returns:
        ``cur_idx (M,)``, ``tgt_idx (M,)`` int indices of the kept matches and their descriptor
        ``distance (M,)`` float32 (nearest neighbour), for the ``M`` matches with
        ``d1 < ratio * d2``.
    """
    if len(cur) == 0 or len(tgt) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros(0, np.float32)
    dist, idx = knn2(cur.des, tgt.des, kind)  # type: ignore[arg-type]
    good = dist[:, 0] < ratio * dist[:, 1]
    q = np.flatnonzero(good)
    return q, idx[q, 0].astype(np.int64), dist[q, 0]


# --------------------------------------------------------------------------------------------------
# threads
# --------------------------------------------------------------------------------------------------
@contextlib.contextmanager
def cv2_num_threads(n: int | None) -> Iterator[None]:
    """Run the block with ``cv2.setNumThreads(n)`` and restore the previous value (``None``: no change).

    OpenCV's setting is process-wide; scoping it to the agent's ``act`` keeps e.g. the simulator's
    OpenCV remaps multi-threaded.
    """
    if n is None:
        yield
        return
    prev = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(prev)


class ParallelRunner:
    """Maps a function over slots with a small thread pool (serial for 1 thread or 1 item)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, int(threads))
        self._pool: ThreadPoolExecutor | None = None

    def map(self, fn: Callable[[_T], _R], items: Sequence[_T]) -> list[_R]:
        if self.threads <= 1 or len(items) <= 1:
            return [fn(x) for x in items]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.threads, thread_name_prefix="findview-agent")
        return list(self._pool.map(fn, items))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


# --------------------------------------------------------------------------------------------------
# the base agent
# --------------------------------------------------------------------------------------------------
@dataclass
class Slot:
    """Per-slot state every feature agent has.

    Attributes:
        rng: the episode's random stream (:func:`~findview_baselines.agents.base.episode_rng`).
        difficulty: the episode's difficulty (``None`` for an idle slot).
        target: what :meth:`FeatureAgent.prepare_target` kept of the target; ``None`` until computed.
        done: the slot said STOP (or idles): it answers STOP without work until reset.
    """

    rng: np.random.Generator
    difficulty: str | None = None
    target: Any = None
    done: bool = False


class FeatureAgent(Agent):
    """Batched base of the feature-based agents (see the module docstring).

    Args:
        num_envs, device, seed: see :class:`~findview_baselines.agents.base.Agent`.
        threads: worker threads over slots (OpenCV releases the GIL).
        cv2_threads: OpenCV threads while the agent acts on several slots (1: the slot threads do the
            parallel work; ``None`` leaves OpenCV's setting alone). Restored after each ``act``; a step
            with a single slot to process keeps OpenCV's own setting.
    """

    name = "feature"
    #: the config keys :meth:`from_config` accepts (the constructor's keyword arguments)
    CONFIG_KEYS: tuple[str, ...] = ("threads", "cv2_threads")

    def __init__(
        self,
        num_envs: int,
        device: str | torch.device = "cpu",
        seed: int = 0,
        threads: int = 2,
        cv2_threads: int | None = 1,
    ) -> None:
        super().__init__(num_envs, device, seed)
        self.cv2_threads = None if cv2_threads is None else int(cv2_threads)
        self.runner = ParallelRunner(threads)
        self._rng = np.random.default_rng(self.seed)
        # before the first reset a slot plays an episode it knows nothing about (no difficulty)
        self.slots: list[Any] = [
            self.new_slot(None, episode_rng(self.seed, None, self._rng)) for _ in range(self.num_envs)
        ]

    @classmethod
    def from_config(cls, cfg: Any, num_envs: int, device: str | torch.device, seed: int, **fixed: Any) -> Any:
        """Build from a config mapping (unknown keys raise ``ValueError`` naming the valid ones);
        ``fixed`` are keyword arguments the caller imposes (e.g. ``detector="orb"``)."""
        c = to_plain_dict(cfg)
        check_keys(str(fixed.get("detector", cls.name)), c, cls.CONFIG_KEYS)
        kw = {k: c[k] for k in cls.CONFIG_KEYS if k in c}
        for k, v in fixed.items():
            if k in kw and kw[k] != v:
                raise ValueError(f"agent {v!r}: config sets {k}={kw[k]!r}")
            kw[k] = v
        return cls(num_envs, device, seed, **kw)

    # the decision rule (subclasses) ---------------------------------------------------------------
    def new_slot(self, episode: Episode | None, rng: np.random.Generator) -> Slot:
        """The state of a slot starting ``episode`` (``rng``: its random stream)."""
        return Slot(rng=rng, difficulty=None if episode is None else episode.difficulty)

    def prepare_target(self, slot: Slot, target: np.ndarray) -> Any:
        """What the rule keeps of the ``(3, H, W)`` uint8 target image (stored in ``slot.target``)."""
        raise NotImplementedError

    def wants_view(self, slot: Slot) -> bool:
        """Whether the slot looks at its current view this step (``False``: :meth:`step` gets ``None``)."""
        return True

    def step(self, i: int, slot: Slot, view: np.ndarray | None) -> int:
        """The action of slot ``i`` given its ``(3, H, W)`` uint8 view (``None``: not requested)."""
        raise NotImplementedError

    # machinery -----------------------------------------------------------------------------------
    @light_work()
    def reset(self, env_ids: Sequence[int], episodes: Sequence[Episode | None]) -> None:
        """Start ``episodes`` in slots ``env_ids``; a ``None`` episode idles the slot (STOP, no work)."""
        super().reset(env_ids, episodes)
        for i, ep in zip(env_ids, episodes):
            s = self.new_slot(ep, episode_rng(self.seed, ep, self._rng))
            s.done = ep is None
            self.slots[int(i)] = s

    @light_work()
    def act(self, obs: Mapping[str, torch.Tensor]) -> torch.Tensor:
        view, target = self._check_obs(obs)
        actions = np.full(self.num_envs, STOP, dtype=np.int64)
        active = [i for i, s in enumerate(self.slots) if not s.done]
        if not active:
            return self._as_actions(actions, view.device)
        look = [i for i in active if self.wants_view(self.slots[i])]
        need_t = [i for i in look if self.slots[i].target is None]
        views = host_images(view, look) if look else None
        targets = host_images(target, need_t) if need_t else None
        pos_v = {i: k for k, i in enumerate(look)}
        pos_t = {i: k for k, i in enumerate(need_t)}

        def run(i: int) -> int:
            s = self.slots[i]
            if i not in pos_v:
                return self.step(i, s, None)
            if s.target is None:
                s.target = self.prepare_target(s, targets[pos_t[i]])  # type: ignore[index]
            return self.step(i, s, views[pos_v[i]])  # type: ignore[index]

        # one slot: let OpenCV parallelise inside it; several: one slot per worker thread
        with cv2_num_threads(self.cv2_threads if len(look) > 1 else None):
            results = self.runner.map(run, look)
        for i, a in zip(look, results):
            actions[i] = a
        for i in active:
            if i not in pos_v:
                actions[i] = run(i)
        return self._as_actions(actions, view.device)

    def close(self) -> None:
        """Stop the worker threads."""
        self.runner.close()
